"""The README's script examples run as written: every python block of its "From a script"
section, in order in one namespace, against a small scene, with the installed package's
import path (bl_ext.user_default.hybrid_raycast) pointing at this checkout."""

import re
import sys
import types
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import addon, fresh, simple_scene  # noqa: E402,F401

pytestmark = pytest.mark.blender

README = Path(__file__).resolve().parents[1] / "README.md"


def script_blocks() -> list[str]:
    text = README.read_text()
    start = text.index("### From a script")
    end = text.index("\n## ", start)
    return re.findall(r"```python\n(.*?)```", text[start:end], flags=re.S)


def test_the_script_section_has_examples():
    blocks = script_blocks()
    assert len(blocks) >= 2 and all("api." in b for b in blocks)


def test_readme_script_examples_run_as_written(fresh, addon, monkeypatch):
    for name in ("bl_ext", "bl_ext.user_default"):
        mod = types.ModuleType(name)
        mod.__path__ = []
        monkeypatch.setitem(sys.modules, name, mod)
    monkeypatch.setitem(sys.modules, "bl_ext.user_default.hybrid_raycast", addon)
    simple_scene()
    namespace = {}
    for i, block in enumerate(script_blocks()):
        try:
            exec(compile(block, f"README.md script block {i + 1}", "exec"), namespace)
        except Exception as e:  # report which block, then fail with the original error
            raise AssertionError(f"README script block {i + 1} failed: {type(e).__name__}: {e}") from e
    r = namespace["r"]
    assert r.hit.any() and len(namespace["hit_objects"]) == r.hit.sum()
    assert {ob.name for ob in namespace["hit_objects"]} <= {"Cube", "Ground"}
    assert np.array_equal(namespace["layers"].count > 0, r.hit[:100])
