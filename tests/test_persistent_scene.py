"""The scene persists across frames and calls: a frame where nothing moved keeps the session,
a frame that changed reads again only the meshes that changed, and every result still equals
a fresh extraction of the scene as it is now."""

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_cube, add_plane, addon, fresh  # noqa: E402,F401

pytestmark = pytest.mark.blender


def _scene():
    """A ground, a static cube, a waving grid (deforms every frame), a cube keyframed to
    move, and an Empty keyframed to move (brings no triangles)."""
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 1, 20
    add_plane("Ground", 20.0, z=-1.0)
    add_cube("Static", 1.0, (2.0, 0.0, 0.0))
    wave = add_plane("Wave", 4.0, z=0.0, location=(-3.0, 0.0, 0.0), subdivisions=16)
    wave.modifiers.new("w", "WAVE")
    mover = add_cube("Mover", 1.0, (0.0, 3.0, 0.0))
    empty = bpy.data.objects.new("Rig", None)
    scene.collection.objects.link(empty)
    for ob, frame, x in ((empty, 1, 0.0), (empty, 20, 5.0)):
        ob.location.x = x
        ob.keyframe_insert("location", frame=frame)
    scene.frame_set(1)
    return scene, wave, mover, empty


def _rays(n=400, seed=0):
    rng = np.random.default_rng(seed)
    o = np.stack([rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), np.full(n, 5.0)], axis=1)
    d = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), -np.ones(n)], axis=1)
    return o, d


def _reads(addon, monkeypatch):
    """Count the evaluated meshes extraction reads (``extract._mesh_triangles``)."""
    ext = addon.operators.extract
    seen = []
    real = ext._mesh_triangles

    def counting(me):
        seen.append(me.name)
        return real(me)

    monkeypatch.setattr(ext, "_mesh_triangles", counting)
    return seen


def _fresh_flat(addon, o, d):
    """The same rays through a flat world-space extraction made now, with the float64 brute force."""
    ext, core = addon.operators.extract, addon.core
    mesh = ext.scene_mesh(bpy.context.evaluated_depsgraph_get())
    return mesh, core.build(mesh, "brute").trace(o, d)


def test_a_frame_where_nothing_moved_keeps_the_session_and_its_structures(fresh, addon, monkeypatch):
    scene, wave, mover, empty = _scene()
    wave.modifiers.clear()  # nothing deforms; only an Empty moves
    scene.frame_set(1)
    session = addon.operators.session
    o, d = _rays()
    first = addon.api.cast(o, d, structure="grid")
    s1 = session.get(bpy.context.evaluated_depsgraph_get())
    reads = _reads(addon, monkeypatch)
    scene.frame_set(7)
    again = addon.api.cast(o, d, structure="grid")
    s7 = session.get(bpy.context.evaluated_depsgraph_get())
    assert s7 is s1, "a frame that moved only an Empty started a new session"
    assert reads == [], f"meshes read again: {reads}"
    assert np.array_equal(first.t, again.t) and np.array_equal(first.triangle, again.triangle)
    assert s7.summary["frame"] == 7


def test_a_changed_frame_reads_again_only_the_mesh_that_changed(fresh, addon, monkeypatch):
    scene, wave, mover, empty = _scene()
    o, d = _rays()
    addon.api.cast(o, d, structure="grid")
    reads = _reads(addon, monkeypatch)
    scene.frame_set(5)
    r = addon.api.cast(o, d, structure="grid")
    assert reads == ["Wave"], f"a frame where only the wave deformed read {reads}"
    mesh, ref = _fresh_flat(addon, o, d)
    assert np.array_equal(r.hit, ref.hit), "hits differ from a fresh extraction"
    assert np.allclose(r.t[ref.hit], ref.t[ref.hit], rtol=1e-5, atol=1e-5)
    assert np.array_equal(r.triangle, ref.triangle), "triangle numbering differs from a fresh extraction"
    reads.clear()
    mover.location.x += 1.5  # moved rigidly, nothing deforms at this frame
    r = addon.api.cast(o, d, structure="grid")
    assert "Mover" not in reads, f"a rigid move read the moved mesh again: {reads}"
    mesh, ref = _fresh_flat(addon, o, d)
    assert np.array_equal(r.hit, ref.hit) and np.allclose(r.t[ref.hit], ref.t[ref.hit], rtol=1e-5, atol=1e-5)


def test_meshes_no_session_uses_are_forgotten(fresh, addon):
    scene, wave, mover, empty = _scene()
    session = addon.operators.session
    o, d = _rays()
    for frame in range(1, 8):
        scene.frame_set(frame)
        addon.api.cast(o, d, structure="grid")
    live = {g.key for s in session.SESSIONS.values() for g in s.layout.groups}
    assert set(session.MESHES) == live, "the mesh cache keeps meshes of past frames"
    assert len(session.MESHES) == 4


def test_a_later_frame_inherits_the_plan_instead_of_planning_again(fresh, addon):
    scene, wave, mover, empty = _scene()
    o, d = _rays()
    first = addon.api.cast(o, d)
    scene.frame_set(9)
    later = addon.api.cast(o, d)
    assert later.plan is first.plan, "a frame that deformed one mesh planned again"
    mesh, ref = _fresh_flat(addon, o, d)
    assert np.array_equal(later.hit, ref.hit)
