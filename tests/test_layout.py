"""Project rules that keep the package installable and core testable without Blender."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"bpy", "mathutils", "bmesh", "gpu", "bpy_extras", "aud", "bl_math"}


def _imports(path):
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name, 0
        elif isinstance(node, ast.ImportFrom):
            yield node.lineno, node.module or "", node.level


def test_core_never_imports_blender_modules():
    bad = [
        f"{p.relative_to(ROOT)}:{line} imports {mod}"
        for p in sorted((ROOT / "core").rglob("*.py"))
        for line, mod, level in _imports(p)
        if level == 0 and mod.split(".")[0] in FORBIDDEN
    ]
    assert not bad, "core/ must stay pure numpy:\n" + "\n".join(bad)


def _package_files():
    """Every module that ships in the extension: top-level modules and core/, operators/, ui/."""
    yield from sorted(ROOT.glob("*.py"))
    for sub in ("core", "operators", "ui"):
        yield from sorted((ROOT / sub).rglob("*.py"))


def test_package_uses_only_relative_imports_of_itself():
    files = list(_package_files())
    assert any(p.name == "api.py" for p in files) and any(p.name == "__init__.py" for p in files)
    bad = [
        f"{p.relative_to(ROOT)}:{line} imports {mod}"
        for p in files
        for line, mod, level in _imports(p)
        if level == 0 and mod.split(".")[0] in {"hybrid_raycast", "bl_ext"}
    ]
    assert not bad, "the installed package is bl_ext.<repo>.hybrid_raycast; use relative imports:\n" + "\n".join(bad)
