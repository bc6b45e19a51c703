"""Build the per-platform zips with Blender's own tool, validate them, and install them as a user would.

``blender_ext.py build --split-platforms`` makes one zip per platform of the manifest and gives
each the wheels whose platform tag names it (``blender_platforms_from_wheel_platform``): embreex
has wheels for linux-x64 and windows-x64 only, so the macOS and linux-arm64 zips are numpy-only.
Blender refuses to install a zip built for another platform ("This platform (linux-x64) isn't
one of (linux-arm64)", bpy 5.0.1), so the numpy-only package is installed here as the
linux-arm64 zip with only its generated platform line changed to this machine's: the same files
(checked below), the same absent wheels.
"""

import json
import os
import platform
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.blender, pytest.mark.slow]

#: the wheels each platform's package must carry (the manifest's embreex wheels, by tag)
EXPECTED_WHEELS = {
    "linux-x64": ("manylinux", "x86_64.whl"),
    "windows-x64": ("win_amd64.whl",),
    "macos-arm64": None,
    "macos-x64": None,
    "linux-arm64": None,
}


def _this_platform():
    system = {"darwin": "macos"}.get(platform.system().lower(), platform.system().lower())
    machine = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64"}.get(platform.machine().lower(), platform.machine().lower())
    return f"{system}-{machine}"


def _blender_scripts():
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None:
        pytest.skip("bpy (Blender as a Python module) is not installed")
    # bpy keeps Blender's scripts in a folder named after its version (bpy/4.2/scripts, bpy/5.0/scripts)
    found = sorted(Path(spec.origin).parent.glob("[0-9]*.[0-9]*/scripts"))
    assert len(found) == 1, f"expected one bpy/<version>/scripts folder, found {found}"
    return found[0]


def _manifest():
    import tomllib

    return tomllib.loads((ROOT / "blender_manifest.toml").read_text())


def _missing_wheels():
    return [w for w in _manifest().get("wheels", []) if not (ROOT / w).is_file()]


@pytest.fixture(scope="module")
def built_zips(tmp_path_factory):
    """{platform: zip path}, built by blender_ext.py build --split-platforms."""
    missing = _missing_wheels()
    if missing:
        pytest.fail(f"bundled wheels missing (run `make wheels`): {missing}")
    scripts = _blender_scripts()
    tool = scripts / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"
    tags = scripts / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    out = tmp_path_factory.mktemp("dist")
    v = subprocess.run([sys.executable, tool, "validate", "--valid-tags", tags, ROOT], capture_output=True, text=True)
    assert v.returncode == 0, f"blender_ext.py validate failed:\n{v.stdout}\n{v.stderr}"
    b = subprocess.run(
        [sys.executable, tool, "build", "--split-platforms", "--valid-tags", tags, "--source-dir", ROOT, "--output-dir", out],
        capture_output=True, text=True,
    )
    assert b.returncode == 0, f"blender_ext.py build failed:\n{b.stdout}\n{b.stderr}"
    version = _manifest()["version"]
    zips = {p: out / f"hybrid_raycast-{version}-{p.replace('-', '_')}.zip" for p in _manifest()["platforms"]}
    absent = [str(z) for z in zips.values() if not z.is_file()]
    assert not absent, f"blender_ext.py build made {sorted(x.name for x in out.iterdir())}, not {absent}"
    return zips


def _generated(zf):
    """The [build.generated] platforms and wheels blender_ext.py wrote into a split zip's manifest."""
    import tomllib

    gen = tomllib.loads(zf.read("blender_manifest.toml").decode())["build"]["generated"]
    return gen["platforms"], gen["wheels"]


def test_manifest_lists_every_platform_the_packages_are_built_for():
    assert sorted(_manifest()["platforms"]) == sorted(EXPECTED_WHEELS)


def test_each_platform_package_carries_its_own_embreex_wheels_and_no_tests(built_zips):
    for plat, path in built_zips.items():
        zf = zipfile.ZipFile(path)
        names = zf.namelist()
        assert "blender_manifest.toml" in names and "__init__.py" in names, plat
        assert any(n.startswith("core/") for n in names) and any(n.startswith("operators/") for n in names), plat
        leaked = [n for n in names if n.split("/")[0] in {"tests", "scripts", ".ci", ".venv", ".git", "requirements"}
                  or "__pycache__" in n or n == "conftest.py"]
        assert not leaked, f"the {plat} zip carries files a user does not need: {leaked[:10]}"
        assert not any(n.startswith("wheels/numpy") for n in names), "numpy must never be bundled"
        wheels = sorted(n for n in names if n.startswith("wheels/"))
        want = EXPECTED_WHEELS[plat]
        if want is None:
            assert wheels == [], f"the {plat} package should carry no wheel (embreex has none for it): {wheels}"
        else:
            assert len(wheels) == 2 and all(all(w_ in w for w_ in want) for w in wheels), (plat, wheels)
            assert {re.search(r"-(cp3\d+)-", w).group(1) for w in wheels} == {"cp311", "cp313"}, (plat, wheels)
        platforms, listed = _generated(zf)
        assert platforms == [plat] and sorted(Path(w).name for w in listed) == [Path(w).name for w in wheels], \
            (plat, platforms, listed, wheels)


def test_numpy_only_packages_hold_the_same_files_as_the_linux_one_but_its_wheels(built_zips):
    def files(path):
        zf = zipfile.ZipFile(path)
        return {n: zf.read(n) for n in zf.namelist() if not n.startswith("wheels/") and n != "blender_manifest.toml"}

    linux = files(built_zips["linux-x64"])
    for plat, want in EXPECTED_WHEELS.items():
        other = files(built_zips[plat])
        differ = sorted(set(linux) ^ set(other)) + sorted(n for n in linux.keys() & other.keys() if linux[n] != other[n])
        assert not differ, f"{plat} package differs from linux-x64 beyond its wheels: {differ[:10]}"


def _retagged(src: Path, dst: Path, platform_name: str) -> Path:
    """``src`` with only its generated ``platforms`` line naming ``platform_name``."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            data = zin.read(info)
            if info.filename == "blender_manifest.toml":
                head, sep, generated = data.decode().partition("[build.generated]")
                generated, n = re.subn(r'(?m)^platforms = \[.*\]$', f'platforms = ["{platform_name}"]', generated)
                assert sep and n == 1, f"no generated platforms line in {src.name}'s manifest"
                data = (head + sep + generated).encode()
            zout.writestr(info, data)
    return dst


def _roundtrip(zip_path, tmp_path):
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    r = subprocess.run(
        [sys.executable, ROOT / "tests" / "install_roundtrip.py", zip_path],
        capture_output=True, text=True, env=env, timeout=600,
    )
    line = next((x for x in r.stdout.splitlines() if x.startswith("ROUNDTRIP ")), None)
    assert r.returncode == 0 and line, f"install round-trip failed (rc {r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return json.loads(line.removeprefix("ROUNDTRIP "))


COMMON = {
    "install": ["FINISHED"],
    "enabled_after_install": True,
    "operator_registered": True,
    "scene_property": True,
    "panel_registered": True,
    "summary_result": ["FINISHED"],
    "triangles_default_cube": 12,
    "analyze_result": ["FINISHED"],
    "enabled_after_toggle": True,
    "uninstall": ["FINISHED"],
    "enabled_after_uninstall": False,
    "operator_after_uninstall": False,
    "scene_property_after_uninstall": False,
}


def _diff(seen, expected):
    return {k: (seen.get(k), v) for k, v in expected.items() if seen.get(k) != v}


def test_this_platforms_package_installs_and_offers_embree_from_its_own_wheel(built_zips, tmp_path):
    here = _this_platform()
    if EXPECTED_WHEELS.get(here) is None:
        pytest.skip(f"{here}: no embreex wheel in this platform's package")
    seen = _roundtrip(built_zips[here], tmp_path)
    expected = dict(COMMON, embree_available=True, embree_unavailable=None, embreex_from="extensions",
                    candidates_weighed=["bvh", "embree", "grid"], record_embree_unavailable=None,
                    panel_embree_unavailable="")
    diff = _diff(seen, expected)
    assert not diff, f"install round-trip of the {here} package differs (seen, expected): {diff}"


def test_numpy_only_package_installs_and_decides_between_grid_and_bvh(built_zips, tmp_path):
    src = built_zips["linux-arm64"]
    seen = _roundtrip(_retagged(src, tmp_path / src.name, _this_platform()), tmp_path)
    reason = "embreex is not installed"  # a wheel exists for this machine; the package did not bring it
    expected = dict(COMMON, embree_available=False, embree_unavailable=reason,
                    candidates_weighed=["bvh", "grid"], record_embree_unavailable=reason,
                    panel_embree_unavailable=reason)
    diff = _diff(seen, expected)
    assert not diff, f"install round-trip of the numpy-only package differs (seen, expected): {diff}"
    assert f"Embree unavailable: {reason}; deciding between the grid and the BVH" in seen["notes"], seen["notes"]
