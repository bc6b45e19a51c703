"""register()/unregister() are clean: twice in a row, nothing left behind."""

import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from conftest import load_addon  # noqa: E402

pytestmark = pytest.mark.blender


def _ours():
    return sorted(n for n in dir(bpy.types) if "hybrid_raycast" in n.lower() or n.startswith("HybridRaycast"))


def test_register_unregister_twice_leaves_nothing_behind():
    addon = load_addon()
    before = _ours()
    assert not hasattr(bpy.types.Scene, "hybrid_raycast")
    for round_ in range(2):
        addon.register()
        assert hasattr(bpy.types.Scene, "hybrid_raycast"), f"round {round_}: scene property missing after register"
        for cls in addon.classes:
            assert cls.is_registered, f"round {round_}: {cls.__name__} not registered"
        assert hasattr(bpy.ops.hybrid_raycast, "scene_summary")
        assert bpy.context.scene.hybrid_raycast.expected_rays >= 0
        addon.unregister()
        assert not hasattr(bpy.types.Scene, "hybrid_raycast"), f"round {round_}: scene property left behind"
        left = [c.__name__ for c in addon.classes if c.is_registered]
        assert not left, f"round {round_}: classes left registered: {left}"
        assert _ours() == before, f"round {round_}: bpy.types gained {set(_ours()) - set(before)}"


def test_every_setting_has_a_name_and_description():
    addon = load_addon()
    props = addon.settings.HybridRaycastSettings.__annotations__
    missing = [
        name for name, p in props.items()
        if not p.keywords.get("name") or not p.keywords.get("description")
    ]
    assert not missing, f"settings without a name or description: {missing}"
