"""`pip install .` gives hybrid_raycast.core in a plain Python: no Blender, no tests or scripts.

The install test builds a fresh virtual environment (no system site-packages), installs
numpy and the package into it, and traces a cube there from outside the checkout.
"""

import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

#: copied into the build folder: what a user's checkout holds, less what never ships
_IGNORE = shutil.ignore_patterns(".git", ".venv", "wheels", "dist", "out", "build", "*.egg-info", "__pycache__",
                                 ".cache", ".pytest_cache", ".hypothesis", "docs")

CHECK = r"""
import importlib.metadata, json, sys
import numpy as np
from hybrid_raycast import core
import hybrid_raycast

# a 2-unit cube at the origin; rays from x = -5 towards +x at random (y, z) inside the face
v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float32)
quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
mesh = core.TriangleMesh(v, tris)
rng = np.random.default_rng(0)
yz = rng.uniform(-0.9, 0.9, size=(1000, 2))
o = np.column_stack([np.full(1000, -5.0), yz]).astype(np.float32)
d = np.tile(np.float32([1, 0, 0]), (1000, 1))
out = {}
for kind in ("grid", "bvh"):
    h = core.build(mesh, kind).trace(o, d)
    out[kind] = [bool(h.hit.all()), float(np.abs(h.t - 4.0).max())]
path = core.save_mesh(mesh, sys.argv[1], frame=3)
cal, message = core.load_or_default(None)
print("RESULT " + json.dumps({
    "traces": out, "frame": core.read_scene(path).frame, "calibration": cal.source,
    "bpy_imported": "bpy" in sys.modules, "package_file": hybrid_raycast.__file__,
    "version": importlib.metadata.version("hybrid_raycast"),
    "manifest_version": core.decide.package_version(),
    "requires": importlib.metadata.requires("hybrid_raycast"),
    "files": sorted(str(f) for f in importlib.metadata.files("hybrid_raycast") if f.suffix in (".py", ".json", ".toml")),
}))
"""


def _run(cmd, cwd, timeout=300):
    r = subprocess.run([str(c) for c in cmd], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                       env={k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")})
    assert r.returncode == 0, f"{' '.join(map(str, cmd))} failed ({r.returncode}):\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return r.stdout


def test_pyproject_carries_the_manifest_version_and_the_zip_leaves_build_files_out():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    assert project["project"]["version"] == manifest["version"]
    excluded = manifest["build"]["paths_exclude_pattern"]
    for pattern in ("/pyproject.toml", "/build/", "*.egg-info/"):
        assert pattern in excluded, f"the extension zip must not carry {pattern}"
    assert any("dask" in r for r in project["project"]["optional-dependencies"]["dask"])


def test_pyproject_lists_every_subpackage_that_ships():
    """setuptools installs only the packages pyproject names (the root is mapped to hybrid_raycast),
    so a new subpackage missing from the list breaks `pip install .` at import time."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    skip = {"tests", "scripts", "docs", "wheels", "out", "dist", "build"}
    found = {"hybrid_raycast"} | {
        "hybrid_raycast." + ".".join(p.parent.relative_to(ROOT).parts)
        for p in ROOT.rglob("__init__.py")
        if p.parent != ROOT and p.parent.relative_to(ROOT).parts[0] not in skip
        and not p.parent.relative_to(ROOT).parts[0].startswith(".")
    }
    assert found == listed, f"packages to add to pyproject: {sorted(found - listed)}; listed but absent: {sorted(listed - found)}"


@pytest.mark.slow
def test_pip_install_gives_the_core_in_a_fresh_venv_without_blender(tmp_path):
    src = tmp_path / "checkout"
    shutil.copytree(ROOT, src, ignore=_IGNORE, symlinks=True)
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", venv], tmp_path)
    py = venv / "bin" / "python"
    # numpy as this environment has it (pip's cache usually holds the wheel), then the package
    _run([py, "-m", "pip", "install", "-q", "--disable-pip-version-check", f"numpy=={np.__version__}"], tmp_path)
    _run([py, "-m", "pip", "install", "-q", "--disable-pip-version-check", src], tmp_path)  # as a user would
    work = tmp_path / "elsewhere"
    work.mkdir()
    out = _run([py, "-c", CHECK, work / "cube.npz"], work)
    got = json.loads(next(x for x in out.splitlines() if x.startswith("RESULT ")).removeprefix("RESULT "))
    for kind, (all_hit, err) in got["traces"].items():
        assert all_hit and err < 1e-5, f"{kind}: rays from x=-5 into the cube face at x=-1 must hit at t=4 ({got})"
    assert got["frame"] == 3 and got["calibration"] == "shipped defaults"
    assert got["bpy_imported"] is False, "importing the core must not import bpy"
    assert str(venv) in got["package_file"], f"imported from {got['package_file']}, not the installed copy"
    assert got["version"] == got["manifest_version"], "the installed package reads the version from its manifest"
    assert any(re.match(r"dask\b.*extra == \"dask\"", r) for r in got["requires"]), got["requires"]
    files = got["files"]
    assert "hybrid_raycast/core/default_calibration.json" in files and "hybrid_raycast/api.py" in files
    assert "hybrid_raycast/operators/cli.py" in files and "hybrid_raycast/ui/panel.py" in files
    leaked = [f for f in files if f.split("/")[1] in ("tests", "scripts", "docs")]
    assert not leaked, f"the installed package carries {leaked[:5]}"
