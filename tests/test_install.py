"""Build the extension zip with Blender's own tool, validate it, and install it as a user would."""

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.blender, pytest.mark.slow]


def _blender_scripts():
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None:
        pytest.skip("bpy (Blender as a Python module) is not installed")
    return Path(spec.origin).parent / "5.0" / "scripts"


def _missing_wheels():
    import tomllib

    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    return [w for w in manifest.get("wheels", []) if not (ROOT / w).is_file()]


@pytest.fixture(scope="module")
def built_zip(tmp_path_factory):
    missing = _missing_wheels()
    if missing:
        pytest.fail(f"bundled wheels missing (run `make wheels`): {missing}")
    scripts = _blender_scripts()
    tool = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    out = tmp_path_factory.mktemp("dist") / "hybrid_raycast.zip"
    v = subprocess.run([sys.executable, tool, "validate", "--valid-tags", tags, ROOT], capture_output=True, text=True)
    assert v.returncode == 0, f"blender_ext.py validate failed:\n{v.stdout}\n{v.stderr}"
    b = subprocess.run(
        [sys.executable, tool, "build", "--valid-tags", tags, "--source-dir", ROOT, "--output-filepath", out],
        capture_output=True, text=True,
    )
    assert b.returncode == 0 and out.is_file(), f"blender_ext.py build failed:\n{b.stdout}\n{b.stderr}"
    return out


def test_zip_carries_the_package_and_wheels_but_no_tests(built_zip):
    names = zipfile.ZipFile(built_zip).namelist()
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert any(n.startswith("core/") for n in names) and any(n.startswith("operators/") for n in names)
    leaked = [n for n in names if n.split("/")[0] in {"tests", "scripts", ".ci", ".venv", ".git"} or "__pycache__" in n]
    assert not leaked, f"the zip carries files a user does not need: {leaked[:10]}"
    assert not any(n.startswith("wheels/numpy") for n in names), "numpy must never be bundled"
    assert sum(n.startswith("wheels/embreex-") for n in names) == 4


def test_install_enable_toggle_and_uninstall_in_blender(built_zip, tmp_path):
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    r = subprocess.run(
        [sys.executable, ROOT / "tests" / "install_roundtrip.py", built_zip],
        capture_output=True, text=True, env=env, timeout=600,
    )
    line = next((x for x in r.stdout.splitlines() if x.startswith("ROUNDTRIP ")), None)
    assert r.returncode == 0 and line, f"install round-trip failed (rc {r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    seen = json.loads(line.removeprefix("ROUNDTRIP "))
    expected = {
        "install": ["FINISHED"],
        "enabled_after_install": True,
        "operator_registered": True,
        "scene_property": True,
        "panel_registered": True,
        "summary_result": ["FINISHED"],
        "triangles_default_cube": 12,
        "enabled_after_toggle": True,
        "uninstall": ["FINISHED"],
        "enabled_after_uninstall": False,
        "operator_after_uninstall": False,
        "scene_property_after_uninstall": False,
    }
    diff = {k: (seen.get(k), v) for k, v in expected.items() if seen.get(k) != v}
    assert not diff, f"install round-trip differs (seen, expected): {diff}"
