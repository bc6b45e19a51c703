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


def _module_of(parts, root=ROOT):
    """The module file a package-relative path names: ``('core', 'plan')`` is core/plan.py,
    ``('core', 'decide')`` is core/decide/__init__.py; None when it is neither (a name
    imported from a module, not a module)."""
    if not parts:
        parts = ("__init__",)
    as_file = root.joinpath(*parts[:-1], parts[-1] + ".py")
    if as_file.is_file():
        return as_file.relative_to(root)
    as_package = root.joinpath(*parts, "__init__.py")
    return as_package.relative_to(root) if as_package.is_file() else None


def import_graph(root=ROOT, files=None):
    """{module file: {module files it imports}} over the package's relative imports,
    including those inside functions (a lazy import is still a dependency): ``from .a
    import b`` depends on a.py, and on a/b.py too when b is a submodule."""
    graph = {}
    for p in files if files is not None else _package_files():
        rel = p.relative_to(root)
        deps = graph.setdefault(rel, set())
        pkg = list(rel.parent.parts)
        for node in ast.walk(ast.parse(p.read_text(), str(p))):
            if not isinstance(node, ast.ImportFrom) or node.level == 0:
                continue
            base = pkg[:len(pkg) - (node.level - 1)] if node.level > 1 else pkg
            mod = tuple(base + (node.module.split(".") if node.module else []))
            found = _module_of(mod, root)
            if node.module:
                deps.add(found)
            for a in node.names:  # a submodule, else a name defined in mod itself
                sub = _module_of(mod + (a.name,), root)
                deps.add(sub if sub is not None else found)
        deps -= {rel, None}
    return graph


def import_cycles(graph) -> list[list]:
    """Every strongly connected set of two or more modules (Tarjan), each as a sorted list:
    a module in one can reach every other and be reached back."""
    index, low, on, stack, out = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(map(str, group)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle_anywhere_in_the_package():
    """Imports run one way inside the layers too: no module reaches itself through the
    package's imports, lazy ones included (a package's __init__ counts as a module)."""
    cycles = import_cycles(import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_rule_finds_a_cycle_through_a_lazy_import(tmp_path):
    """The rule above on a made-up package: a.py imports b at the top, b.py imports a inside
    a function, c.py imports both; the cycle is a <-> b and nothing else."""
    (tmp_path / "core").mkdir()
    (tmp_path / "core" / "__init__.py").write_text("")
    (tmp_path / "core" / "a.py").write_text("from .b import thing\n")
    (tmp_path / "core" / "b.py").write_text("def f():\n    from . import a\n    return a\n")
    (tmp_path / "core" / "c.py").write_text("from .a import thing\nfrom . import b\n")
    files = sorted((tmp_path / "core").glob("*.py"))
    graph = import_graph(tmp_path, files)
    assert graph[Path("core/c.py")] == {Path("core/a.py"), Path("core/b.py")}, graph
    assert import_cycles(graph) == [["core/a.py", "core/b.py"]]
    (tmp_path / "core" / "b.py").write_text("def f():\n    return 1\n")
    assert import_cycles(import_graph(tmp_path, files)) == []


def test_importing_the_package_and_its_api_never_imports_bpy(tmp_path):
    """``pip install .`` gives the core without Blender: importing the package, its core and
    ``api`` (whose functions import the Blender parts on first use) must not import bpy."""
    import subprocess
    import sys

    (tmp_path / "hybrid_raycast").symlink_to(ROOT, target_is_directory=True)
    code = ("import sys; import hybrid_raycast, hybrid_raycast.core, hybrid_raycast.api as api; "
            "assert 'cast' in dir(api); print(sorted(m for m in ('bpy', 'mathutils') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", f"importing the package imported {out.stdout.strip()}"
