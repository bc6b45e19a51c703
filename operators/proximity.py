"""The Bake Proximity operator: each vertex of the active mesh gets its distance to the
nearest other visible geometry, or its signed distance to a chosen object (negative inside,
by the generalized winding number), in a float attribute (point domain) of its mesh.

The distances are measured from the vertices where a bake writes (``passes.bake_vertices``)
to the session's evaluated triangles of the other objects (or of the chosen one), exact in
float64 (``core.Accel.closest``).  A job: progress in the panel, Esc cancels with nothing
written, and the write is one undo step.
"""

from __future__ import annotations

import math

import bpy
import numpy as np

from .. import core
from . import passes, session
from .session import evaluated as evaluated_depsgraph
from .jobs import BadInput, Job, JobOperator, NoGeometry

#: the attribute the bake writes unless told otherwise
ATTRIBUTE = "HRC Proximity"


def proximity_job(scene, job: Job, *, view_layer=None, target=None, to_object: str = "", attribute: str = ATTRIBUTE,
                  max_distance: float = 0.0):
    """Generator: the active (or ``target``) mesh's vertices against the others' triangles."""
    if not attribute:
        raise BadInput("the proximity bake needs an attribute name")
    depsgraph = evaluated_depsgraph(scene, view_layer)
    vl = view_layer if view_layer is not None else depsgraph.view_layer
    ob = passes.ao_target(scene, vl, target, what="the proximity bake")
    other = None
    if to_object:
        other = scene.objects.get(to_object)
        if other is None:
            raise BadInput(f"no object named '{to_object}' in scene '{scene.name}' to measure the signed distance to")
        if other == ob:
            raise BadInput(f"'{ob.name}' cannot be measured against itself: choose another object")
    yield 0.05, "extracting the evaluated triangles"
    s = session.get(depsgraph, scene.hybrid_raycast)
    before = s.fingerprint
    mesh, inst = s.mesh, s.mesh.instances
    tri_owner = inst.instance_object[mesh.instance_index]

    def of(target):  # per triangle: does it belong to ``target``?
        return np.array([o is not None and o.name == target.name for o in inst.objects], bool)[tri_owner]

    if other is not None:
        keep, what = of(other), f"'{other.name}'"
    else:
        keep, what = ~of(ob), f"the geometry other than '{ob.name}'"
    if not keep.any():
        raise NoGeometry(f"no triangles to measure against: {what} has none visible")
    points, _, note = passes.bake_vertices(ob, depsgraph, "measure")
    sub = core.TriangleMesh(mesh.vertices, mesh.triangles[keep])
    md = float(max_distance) if max_distance and max_distance > 0 else math.inf
    if other is not None:  # the sign needs the BVH's winding number: it answers the distances too
        job.fraction, job.text = 0.2, f"building a BVH over {int(keep.sum()):,} triangles"
        acc = yield from job.call(core.build, sub, "bvh")
        job.fraction, job.text = 0.5, f"measuring {len(points):,} vertices"
        near = yield from job.call(acc.closest, points, md)
        kind = "bvh"
    else:  # the decision for point queries: the grid's sample, then the grid or a BVH for the rest
        from .calibrate import load_calibration

        job.fraction, job.text = 0.2, f"building a grid over {int(keep.sum()):,} triangles"
        grid = yield from job.call(core.build, sub, "grid")
        job.fraction, job.text = 0.4, f"measuring {len(points):,} vertices"
        near, kind, _ = yield from job.call(core.decide.points.closest_planned, points, md,
                                            load_calibration()[0].point_model(), grid,
                                            lambda: core.build(sub, "bvh"), sub.triangle_count)
    values = np.where(near.found, near.distance, md if math.isfinite(md) else np.nan)
    if other is not None:
        job.fraction, job.text = 0.8, "signs: the winding number"
        inside = yield from job.call(acc.inside, points)
        values = np.where(inside, -values, values)
    job.check()
    return {"object": ob, "values": values.astype(np.float32), "found": near.found, "to": other,
            "attribute": attribute, "before": before, "view_layer": vl, "max_distance": md, "structure": kind,
            "notes": [note] if note else []}


def write_proximity(ob, values: np.ndarray, attribute: str):
    """Store ``values`` as a FLOAT POINT attribute of ``ob``'s mesh (replacing one of another type)."""
    me = ob.data
    if len(values) != len(me.vertices):
        raise BadInput(f"'{ob.name}' changed while baking ({len(me.vertices)} vertices now, {len(values)} baked)")
    attr = me.attributes.get(attribute)
    if attr is not None and (attr.data_type != "FLOAT" or attr.domain != "POINT"):
        me.attributes.remove(attr)
        attr = None
    if attr is None:
        attr = me.attributes.new(attribute, "FLOAT", "POINT")
    attr.data.foreach_set("value", values)
    me.update()
    return attr


def apply_proximity(scene, result) -> list[tuple[str, str]]:
    ob = result["object"]
    attr = write_proximity(ob, result["values"], result["attribute"])
    session.adopt_own_write(scene, result["view_layer"], result["before"])  # a float attribute moves no triangle
    v = result["values"][result["found"]]
    msgs = [("WARNING", n) for n in result["notes"]]
    missed = int((~result["found"]).sum())
    if missed:
        far = (f"{result['max_distance']:g} (Max Distance)" if math.isfinite(result["max_distance"]) else "NaN")
        msgs.append(("WARNING", f"{missed:,} vertices had nothing within Max Distance: written as {far}"))
    what = f"signed distance to '{result['to'].name}'" if result["to"] is not None else "distance to the nearest other geometry"
    stats = f": min {float(v.min()):.4g}, max {float(v.max()):.4g}" if v.size else ""
    msgs.append(("INFO", f"baked the {what} of {len(result['values']):,} vertices of '{ob.name}' into '{attr.name}'{stats}"
                         f" (searched by the {'grid' if result['structure'] == 'grid' else 'BVH'})"))
    return msgs


class HYBRID_RAYCAST_OT_bake_proximity(JobOperator, bpy.types.Operator):
    """Bake each vertex's distance to the nearest other visible geometry (or its signed distance to a chosen object) into a float attribute of the active mesh"""

    bl_idname = "hybrid_raycast.bake_proximity"
    bl_label = "Bake Proximity"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Hybrid RT proximity bake"

    to_object: bpy.props.StringProperty(
        name="Signed Distance To",
        description="An object to measure the signed distance to (negative inside it); empty: the distance to "
                    "every other visible object",
        default="",
    )
    attribute: bpy.props.StringProperty(
        name="Attribute", description="The float point attribute of the active mesh to write", default=ATTRIBUTE)
    max_distance: bpy.props.FloatProperty(
        name="Max Distance", description="Search no farther; vertices with nothing nearer get this value (0: no limit, "
                                         "and NaN where nothing is found)",
        default=0.0, min=0.0, soft_max=100.0, subtype="DISTANCE", unit="LENGTH")

    def start(self, context, job):
        return proximity_job(context.scene, job, view_layer=context.view_layer, to_object=self.to_object,
                             attribute=self.attribute, max_distance=self.max_distance)

    def finish(self, context, result):
        return apply_proximity(context.scene, result)
