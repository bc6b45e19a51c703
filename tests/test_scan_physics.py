"""Sensor physics in Blender, each against a scene with a known answer: a sweep past a moving
wall, a beam split by an edge, a glass pane, a mirror, fog, and bad settings."""

from __future__ import annotations

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy", reason="bpy (Blender as a Python module) is not installed")

from blender_scenes import add_plane, addon, fresh  # noqa: E402,F401

pytestmark = pytest.mark.blender

FPS = 24


def _wall(name, x, size=40.0, material=None):
    """A vertical square facing -X at ``x``, centred on the X axis."""
    wall = add_plane(name, size, z=0.0, location=(x, 0.0, 0.0))
    wall.rotation_euler = (0.0, math.radians(90.0), 0.0)
    if material is not None:
        wall.data.materials.append(material)
    return wall


def _linear(ob):
    for fc in ob.animation_data.action.fcurves if hasattr(ob.animation_data.action, "fcurves") else []:
        for k in fc.keyframe_points:
            k.interpolation = "LINEAR"


def _animate(ob, path, index, a, b, frames=(1, 25)):
    """Move ob.<path>[index] linearly from a at frames[0] to b at frames[1]."""
    getattr(ob, path)[index] = a
    ob.keyframe_insert(path, index=index, frame=frames[0])
    getattr(ob, path)[index] = b
    ob.keyframe_insert(path, index=index, frame=frames[1])
    ad = ob.animation_data
    curves = []
    if hasattr(ad.action, "fcurves"):
        curves = list(ad.action.fcurves)
    else:  # layered actions (Blender 4.4+)
        for layer in ad.action.layers:
            for strip in layer.strips:
                for bag in strip.channelbags:
                    curves.extend(bag.fcurves)
    for fc in curves:
        for k in fc.keyframe_points:
            k.interpolation = "LINEAR"


def _sensor(kind="ROTATING", **settings):
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = FPS, 1.0
    scene.frame_start, scene.frame_end = 1, 30
    ob = bpy.data.objects.new("Lidar", None)
    scene.collection.objects.link(ob)
    s = ob.hybrid_raycast_sensor
    s.preset = "CUSTOM"
    s.kind = kind
    s.range_min, s.range_max = 0.1, 100.0
    for k, v in settings.items():
        setattr(s, k, v)
    return scene, ob


def _one_beam(scene_sensor_settings=None, **settings):
    """A solid-state sensor with one beam along +X."""
    return _sensor("AREA", h_fov=0.01, v_fov=0.01, h_steps=1, v_steps=1, **settings)


def _material(name, **inputs):
    m = bpy.data.materials.new(name)
    if m.node_tree is None or bpy.app.version < (5, 0, 0):  # before 5.0 a new material has no nodes in use
        m.use_nodes = True
    bsdf = next(n for n in m.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    for key, value in inputs.items():  # 'Transmission' before Blender 4.0
        sock = key if key in bsdf.inputs else key.replace(" Weight", "")
        bsdf.inputs[sock].default_value = value
    return m


# -- a sweep in time ------------------------------------------------------------------------------

def test_sweep_skew_of_a_wall_passing_at_10_m_s_matches_the_analytic_skew(fresh, addon):
    """A wall at x = 10 m moves towards a 10 Hz sensor at 10 m/s: a ray fired t s into the
    sweep sees it at x = 10 - 10 t (frame 1 is scene time 0), to within the 1 cm tolerance."""
    scene, sensor = _sensor(channels=1, fov_up=0.0, fov_down=0.0, azimuth_steps=720, rotation_rate=10.0,
                            motion="SWEEP", sweep_tolerance=0.01)
    wall = _wall("Wall", 10.0)
    _animate(wall, "location", 0, 10.0, 0.0, frames=(1, 1 + FPS))  # 10 m in 1 s
    scene.frame_set(1)
    r = addon.api.scan(sensor)
    on = r.object_names[r.object_index] == "Wall"
    assert on.sum() > 100, f"the wall gave {on.sum()} points"
    t = r.time[on]  # frame 1 is scene time 0: the firing time within the sweep
    expected_x = 10.0 - 10.0 * t
    err = np.abs(r.points[on, 0] - expected_x)
    assert err.max() <= 0.005 + 1e-4, f"skew off the analytic one by up to {err.max():.4f} m (at t={t[err.argmax()]:.4f})"
    skew = r.points[on, 0].max() - r.points[on, 0].min()
    analytic = 10.0 * (t.max() - t.min())
    assert abs(skew - analytic) <= 0.01, f"measured skew {skew:.4f} m, analytic {analytic:.4f} m"
    assert r.blocks >= 90, f"{r.blocks} blocks cannot hold a 1 m sweep motion within 1 cm"
    assert r.extra["rigid_blocks"] == r.blocks, "a wall that only moves: every block places it at its instant"
    sensor.hybrid_raycast_sensor.motion = "FRAME"
    f = addon.api.scan(sensor)
    fon = f.object_names[f.object_index] == "Wall"
    assert np.allclose(f.points[fon, 0], 10.0, atol=1e-3), "FRAME: every ray sees the wall of the frame"
    assert scene.frame_current == 1 and scene.frame_subframe == 0.0, "the scan put the timeline back"


def test_sweep_of_a_moving_sensor_places_a_static_wall_right_in_the_world(fresh, addon):
    """The sensor moves at 10 m/s towards a static wall: in world space every point lies on
    the wall (ego motion per ray); in sensor space the range shrinks by 10 m/s x firing time."""
    scene, sensor = _sensor(channels=1, fov_up=0.0, fov_down=0.0, azimuth_steps=720, rotation_rate=10.0,
                            motion="SWEEP")
    _wall("Wall", 10.0)
    _animate(sensor, "location", 0, 0.0, 10.0, frames=(1, 1 + FPS))
    scene.frame_set(1)
    w = addon.api.scan(sensor)
    on = w.object_names[w.object_index] == "Wall"
    assert np.allclose(w.points[on, 0], 10.0, atol=1e-3), "world points off the static wall"
    assert w.blocks == 1, "only the sensor moves: one block, every ray from its own pose"
    s = addon.api.scan(sensor, space="SENSOR")
    on = s.object_names[s.object_index] == "Wall"
    assert np.allclose(s.points[on, 0], 10.0 - 10.0 * s.time[on], atol=2e-3), "sensor-frame x is the wall's distance then"


def test_sweep_of_a_static_scene_equals_a_frame_scan(fresh, addon):
    scene, sensor = _sensor(channels=4, fov_up=5.0, fov_down=-5.0, azimuth_steps=360)
    _wall("Wall", 10.0)
    add_plane("Ground", 60.0, z=-1.0)
    scene.frame_set(1)
    f = addon.api.scan(sensor)
    sensor.hybrid_raycast_sensor.motion = "SWEEP"
    s = addon.api.scan(sensor)
    assert s.blocks == 1
    assert np.array_equal(f.ray, s.ray)
    assert np.allclose(f.points, s.points, atol=1e-6)


# -- returns ----------------------------------------------------------------------------------------

def test_dual_returns_at_an_edge_give_the_near_and_the_far_surface(fresh, addon):
    """One beam of 4 mrad, 32 samples, its axis on the edge of a near plate at 10 m in front
    of a wall at 20 m: DUAL gives two returns (index 1 and 2 of 2), each with about half the
    intensity of a beam that falls whole on a surface at the same range."""
    scene, sensor = _one_beam(beam_divergence=4.0, beam_samples=32, returns="DUAL", reference_range=100.0,
                              use_materials=False)
    _wall("Far", 20.0)
    near = add_plane("Near", 4.0, z=0.0, location=(10.0, -2.0, 0.0))  # covers y in [-4, 0]: the edge at y = 0
    near.rotation_euler = (0.0, math.radians(90.0), 0.0)
    scene.frame_set(1)
    r = addon.api.scan(sensor)
    assert len(r) == 2, f"DUAL at an edge: {len(r)} returns, ranges {r.range}"
    assert np.allclose(np.sort(r.range), [10.0, 20.0], atol=0.01)
    assert r.return_count.tolist() == [2, 2] and sorted(r.return_index.tolist()) == [1, 2]
    names = set(r.object_names[r.object_index])
    assert names == {"Near", "Far"}
    # whole beam on the far wall for reference: intensity 1 x falloff (reference 100 m: none)
    assert np.all((r.intensity > 0.3) & (r.intensity < 0.7)), f"each return holds about half the beam: {r.intensity}"
    for mode, want in (("FIRST", 10.0), ("LAST", 20.0)):
        sensor.hybrid_raycast_sensor.returns = mode
        one = addon.api.scan(sensor)
        assert len(one) == 1 and abs(one.range[0] - want) < 0.01, f"{mode}: {one.range}"
        assert one.return_count[0] == 1 and one.return_index[0] == 1


def test_a_glass_pane_passes_light_on_to_the_wall_behind(fresh, addon):
    scene, sensor = _one_beam(returns="LAST")
    glass = _material("Glass", **{"Transmission Weight": 0.4, "Base Color": (1, 1, 1, 1)})
    _wall("Wall", 10.0)
    _wall("Pane", 5.0, size=4.0, material=glass)
    scene.frame_set(1)
    last = addon.api.scan(sensor)
    assert len(last) == 1 and abs(last.range[0] - 10.0) < 1e-3, f"LAST through glass: {last.range}"
    assert last.object_names[last.object_index[0]] == "Wall"
    sensor.hybrid_raycast_sensor.returns = "FIRST"
    first = addon.api.scan(sensor)
    assert abs(first.range[0] - 5.0) < 1e-3 and first.point_material_names.tolist() == ["Glass"]
    sensor.hybrid_raycast_sensor.returns = "DUAL"
    dual = addon.api.scan(sensor)
    assert sorted(np.round(dual.range, 3).tolist()) == [5.0, 10.0], "the pane (strongest) and the wall (last)"
    sensor.hybrid_raycast_sensor.use_materials = False
    opaque = addon.api.scan(sensor)
    assert len(opaque) == 1 and abs(opaque.range[0] - 5.0) < 1e-3, "without materials the pane is opaque"


def test_a_mirror_returns_a_ghost_behind_it_when_bounces_are_followed(fresh, addon):
    """A mirror at 5 m turned 45 degrees sends the beam sideways to a wall 3 m off the axis:
    the sensor reports the wall's distance along its own beam, 5 + 3 = 8 m straight ahead."""
    scene, sensor = _one_beam(max_bounces=1, returns="LAST", reference_range=100.0)
    mirror_mat = _material("Mirror", Metallic=1.0, Roughness=0.02, **{"Base Color": (0.9, 0.9, 0.9, 1.0)})
    m = add_plane("Mirror", 2.0, z=0.0, location=(5.0, 0.0, 0.0))
    m.rotation_euler = (math.radians(90.0), 0.0, math.radians(45.0))  # normal in the XY plane at 45 degrees
    m.data.materials.append(mirror_mat)
    side = add_plane("Side", 40.0, z=0.0, location=(5.0, 3.0, 0.0))
    side.rotation_euler = (math.radians(90.0), 0.0, 0.0)  # faces -Y, at y = 3
    scene.frame_set(1)
    r = addon.api.scan(sensor)
    ghost = r.object_names[r.object_index] == "Side"
    assert ghost.any(), f"no ghost return: {r.range} {r.object_names[r.object_index]}"
    assert abs(r.range[ghost][0] - 8.0) < 1e-3
    assert np.allclose(r.points[ghost][0], [8.0, 0.0, 0.0], atol=1e-3), "a ghost lies on the beam, past the mirror"
    sensor.hybrid_raycast_sensor.max_bounces = 0
    flat = addon.api.scan(sensor)
    assert set(flat.object_names[flat.object_index]) == {"Mirror"}


# -- weather and dropout ----------------------------------------------------------------------------

def test_fog_returns_come_at_the_set_rate_near_the_sensor_as_noise(fresh, addon):
    scene, sensor = _sensor(channels=16, azimuth_steps=1000, false_return_rate=0.2, false_return_range=5.0,
                            range_min=0.5, returns="FIRST")  # a fog return is always the nearest
    add_plane("Ground", 100.0, z=-2.0)
    scene.frame_set(1)
    r = addon.api.scan(sensor)
    fog = r.object_index < 0
    share = fog.sum() / 16000
    assert abs(share - 0.2) < 0.015, f"fog returns on {share:.3f} of beams, set 0.2"
    assert r.range[fog].min() >= 0.5 and r.range[fog].max() <= 5.0
    assert (r.classification[fog] == 7).all() and (r.classification[~fog] == 1).all()
    assert set(r.point_object_names[fog]) == {""} and set(r.point_object_names[~fog]) == {"Ground"}
    assert np.isnan(r.normals[fog]).all()


def test_visibility_attenuates_intensity_by_the_two_way_extinction(fresh, addon):
    scene, sensor = _one_beam(reference_range=100.0, use_materials=False)
    _wall("Wall", 20.0)
    scene.frame_set(1)
    clear = addon.api.scan(sensor).intensity[0]
    s = sensor.hybrid_raycast_sensor
    s.use_atmosphere, s.visibility = True, 500.0
    foggy = addon.api.scan(sensor).intensity[0]
    assert abs(foggy / clear - math.exp(-2 * 3.912 / 500.0 * 20.0)) < 1e-4


@pytest.mark.parametrize("name,value,word", [
    ("beam_divergence", -1.0, "beam_divergence"), ("beam_samples", 0, "beam_samples"),
    ("visibility", 0.0, "visibility"), ("mode", "TRIPLE", "mode")])
def test_bad_return_settings_raise_errors_naming_the_setting(addon, name, value, word):
    from hybrid_raycast.core import sensors  # noqa: F401  (the core, as a script would)

    core_sensors = addon.core.sensors
    with pytest.raises((ValueError, TypeError), match=word):
        core_sensors.Returns(**{name: value})


def test_a_bad_reflectivity_property_stops_a_scan_job_with_one_line_naming_it(fresh, addon, tmp_path):
    scene, sensor = _one_beam()
    wall = _wall("Wall", 10.0)
    wall["hybrid_raycast_reflectivity"] = 1.5
    scan = addon.operators.scan
    with pytest.raises(addon.operators.jobs.BadInput, match="hybrid_raycast_reflectivity") as e:
        addon.operators.jobs.run_sync(scan.scan_job(scene, addon.operators.jobs.Job(), sensor, frames=(1, 2),
                                                    directory=str(tmp_path), fmt="ply"))
    assert "frame 1" in str(e.value) and "Lidar" in str(e.value)
    assert not list(tmp_path.iterdir()), "nothing written half-way"


def test_clutter_range_below_range_min_is_refused_before_the_scan(fresh, addon):
    scene, sensor = _sensor(false_return_rate=0.1, false_return_range=0.2, range_min=0.5)
    with pytest.raises(ValueError, match="false_return_range"):
        addon.operators.scan.sensor_settings(sensor)


def test_a_rigid_sweep_moving_its_placements_equals_one_evaluated_block_by_block(fresh, addon, monkeypatch):
    """A sweep where objects only move reads the placements' matrices at each block's instant
    and traces every ray at once, the movers placed at its block's instant; every field equals
    the sweep that extracts and traces each block anew."""
    scene, sensor = _sensor(channels=8, fov_up=10.0, fov_down=-10.0, azimuth_steps=360, motion="SWEEP",
                            sweep_tolerance=0.05)
    _wall("Wall", 10.0)
    mover = add_plane("Mover", 3.0, z=0.0, location=(0.0, 6.0, 0.0))
    mover.rotation_euler = (1.2, 0.3, 0.0)
    mover.scale = (1.0, 2.0, 1.0)  # a non-uniform scale: normals by the inverse transpose
    _animate(mover, "location", 0, -6.0, 6.0, frames=(1, 1 + FPS))
    add_plane("Ground", 60.0, z=-1.5)
    scene.frame_set(1)
    fast = addon.api.scan(sensor)
    assert fast.extra["rigid_blocks"] == fast.blocks > 1
    monkeypatch.setattr(addon.operators.extract.Layout, "rigid_to", lambda self, other: False)
    slow = addon.api.scan(sensor)
    assert slow.extra["rigid_blocks"] == 0 and slow.blocks == fast.blocks
    assert np.array_equal(fast.ray, slow.ray), "another set of beams returned"
    assert np.allclose(fast.points, slow.points, atol=1e-4)
    assert np.allclose(fast.normals, slow.normals, atol=1e-4)
    assert np.array_equal(fast.point_object_names, slow.point_object_names)


def test_a_rigid_sweep_through_glass_from_a_moving_sensor_equals_one_block_by_block(fresh, addon, monkeypatch):
    """The rays that go on through glass keep their instant: a mover seen through a static
    pane, by a sensor that moves too, with DUAL returns, sensor-frame output and
    materials, equals the sweep that extracts and traces each block anew."""
    scene, sensor = _sensor(channels=8, fov_up=10.0, fov_down=-10.0, azimuth_steps=360, motion="SWEEP",
                            sweep_tolerance=0.05, returns="DUAL", use_materials=True)
    _animate(sensor, "location", 1, -0.5, 0.5, frames=(1, 1 + FPS))
    glass = _material("Glass", **{"Transmission Weight": 0.5, "Base Color": (1, 1, 1, 1)})
    pane = add_plane("Pane", 8.0, z=0.0, location=(0.0, 3.0, 0.0))
    pane.rotation_euler = (math.radians(90.0), 0.0, 0.0)
    pane.data.materials.append(glass)
    mover = add_plane("Mover", 3.0, z=0.0, location=(0.0, 6.0, 0.0))
    mover.rotation_euler = (1.2, 0.3, 0.0)
    _animate(mover, "location", 0, -6.0, 6.0, frames=(1, 1 + FPS))
    add_plane("Ground", 60.0, z=-1.5)
    scene.frame_set(1)
    fast = addon.api.scan(sensor, space="SENSOR")
    assert fast.extra["rigid_blocks"] == fast.blocks > 1
    names = fast.point_object_names
    through = (names == "Mover") & (fast.return_count == 2)
    assert through.sum() > 10, f"{through.sum()} DUAL returns behind the pane"
    monkeypatch.setattr(addon.operators.extract.Layout, "rigid_to", lambda self, other: False)
    slow = addon.api.scan(sensor, space="SENSOR")
    assert slow.extra["rigid_blocks"] == 0 and slow.blocks == fast.blocks
    assert np.array_equal(fast.ray, slow.ray) and np.array_equal(fast.return_index, slow.return_index)
    assert np.allclose(fast.points, slow.points, atol=1e-4)
    assert np.allclose(fast.normals, slow.normals, atol=1e-4)
    assert np.array_equal(names, slow.point_object_names)
    assert np.array_equal(fast.point_material_names, slow.point_material_names)


def test_many_beams_from_one_pose_go_on_through_glass(fresh, addon):
    """A FRAME scan (every beam from one origin row) of a pane: the beams that pass it start
    their next leg from their own hit on the pane."""
    scene, sensor = _sensor(channels=8, fov_up=10.0, fov_down=-10.0, azimuth_steps=360, returns="DUAL",
                            use_materials=True)
    glass = _material("Glass", **{"Transmission Weight": 0.5, "Base Color": (1, 1, 1, 1)})
    pane = add_plane("Pane", 8.0, z=0.0, location=(0.0, 3.0, 0.0))
    pane.rotation_euler = (math.radians(90.0), 0.0, 0.0)
    pane.data.materials.append(glass)
    add_plane("Ground", 60.0, z=-1.5)
    scene.frame_set(1)
    r = addon.api.scan(sensor)
    behind = (r.point_object_names == "Ground") & (r.return_count == 2)
    assert behind.sum() > 100, f"{behind.sum()} ground returns behind the pane"
    p = r.points[behind]
    assert np.allclose(p[:, 2], -1.5, atol=1e-4) and (p[:, 1] > 3.0).all(), "a second leg left from elsewhere"
