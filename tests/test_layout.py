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


def _targets(path, root=ROOT):
    """(line, the package-relative module path) of every import of this package in ``path``:
    ``from ..settings import X`` in ``ui/panel.py`` gives ('settings',), ``from .. import ui``
    gives ('ui',)."""
    pkg = list(path.relative_to(root).parent.parts)
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom) or node.level == 0:
            continue
        base = pkg[:len(pkg) - (node.level - 1)] if node.level > 1 else pkg
        if node.module:
            yield node.lineno, tuple(base + node.module.split("."))
        else:
            for a in node.names:
                yield node.lineno, tuple(base + [a.name])


def _layer(parts):
    """The layer a module belongs to: 'core', 'operators', 'ui', or a top-level module's name."""
    first = parts[0]
    return first[:-3] if first.endswith(".py") else first


#: layers each layer must never import (imports run ui -> settings <- operators -> core)
NEVER_IMPORTS = {
    "core": {"operators", "ui", "settings", "budget", "api", "__init__"},
    "ui": {"operators", "api"},
    "operators": {"ui"},
    "settings": {"operators", "ui", "api"},
    "budget": {"operators", "ui", "api", "settings"},
}


def test_imports_run_one_way_ui_to_settings_from_operators_to_core():
    """ui draws from settings and never imports operators; operators never import ui;
    core imports nothing of the package above it; settings and budget sit between."""
    bad = []
    for p in _package_files():
        rel = p.relative_to(ROOT)
        layer = _layer(rel.parts)
        for line, target in _targets(p):
            if target and target[0] in NEVER_IMPORTS.get(layer, ()):
                bad.append(f"{rel}:{line} ({layer}) imports {'.'.join(target)}")
    assert not bad, "imports must run ui -> settings <- operators -> core:\n" + "\n".join(bad)


def test_the_layer_rule_sees_relative_imports_at_any_depth(tmp_path):
    """The rule above is only as good as its import resolver: check it on known cases."""
    f = tmp_path / "ui" / "panel.py"
    f.parent.mkdir()
    f.write_text("from ..operators import jobs\nfrom . import plot\nfrom .. import settings, core\n"
                 "from ..core.plot import plot_rgba\n")
    got = [t for _, t in _targets(f, tmp_path)]
    assert got == [("operators",), ("ui", "plot"), ("settings",), ("core",), ("core", "plot")], got
