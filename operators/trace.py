"""HYBRID_RAYCAST_OT_trace: shoot a workload with the structure the plan picks for it.

Workloads: 'CAMERA' (one ray per pixel of the active camera: the depth, normal and
object-id images of ``passes``) and 'AO' (an ambient-occlusion bake of the active mesh
into a colour attribute).  The ray count of a trace is known, so the trace decides for
*its own* rays: ``core.plan`` with the workload's ray count, timing K of the workload's
own rays through the grid (the paper's representative rays).  The triangles, the grid
and every structure built are kept in the session while its fingerprint is unchanged (``session``), so a
second trace, or one after Analyze, extracts and builds nothing it has already built.
"""

from __future__ import annotations

import time

import bpy
import numpy as np

from .. import core
from . import passes, session
from .analyze import candidate_kinds
from .session import evaluated as evaluated_depsgraph
from .calibrate import load_calibration
from .jobs import BadInput, Job, JobOperator

WORKLOADS = ("CAMERA", "AO")
#: rays per step of the job (progress and Esc between steps).  Every call ends in lockstep
#: steps over its last rays and pays its set-up once, so many small calls cost markedly
#: more than one large call of the same rays, on every structure.  This size keeps that
#: overhead small while a step on a large scene's grid stays short enough for progress and
#: Esc to answer promptly
CHUNK = 1 << 18


def _chunked(job: Job, fn, o, d, tmin, tmax, start: float, span: float):
    """``fn`` over the rays in chunks, reporting progress and honouring cancellation."""
    m = len(o)

    def per(x, a, b):
        x = np.asarray(x)
        return x[a:b] if x.ndim == 1 and len(x) == m else x

    parts = []
    for a in range(0, m, CHUNK):
        b = min(m, a + CHUNK)
        job.progress(start + span * a / max(m, 1), f"tracing rays {a:,}-{b:,} of {m:,}")
        parts.append(fn(o[a:b], d[a:b], per(tmin, a, b), per(tmax, a, b)))
    return parts


def _trace_all(job, acc, rays, any_hit, plan=None):
    """Every ray of the workload through ``acc``, except the plan's sample rays whose
    answers it kept (``Plan.split`` / ``Plan.merge``)."""
    o, d, tmin, tmax = rays["origins"], rays["directions"], rays["tmin"], rays["tmax"]
    m, rest = len(o), None
    t0 = time.perf_counter()
    if plan is not None:
        rest, (o, d, tmin, tmax) = plan.split(o, d, tmin, tmax)
    if any_hit:
        parts = _chunked(job, acc.occluded, o, d, tmin, tmax, 0.5, 0.5)
        out = np.concatenate(parts) if parts else np.zeros(0, bool)
    else:
        parts = _chunked(job, acc.trace, o, d, tmin, tmax, 0.5, 0.5)
        out = core.Hits(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t", "triangle", "u", "v"))) \
            if parts else core.Hits.empty(0)
    traced = m if rest is None else len(rest)
    if plan is not None:
        out = plan.merge(m, rest, out)
    return out, time.perf_counter() - t0, traced


def trace_job(scene, job: Job, *, workload="CAMERA", view_layer=None, target=None, seed=0):
    """Generator: rays for the workload, plan for their count, build (or reuse), trace."""
    workload = str(workload).upper()
    if workload not in WORKLOADS:
        raise BadInput(f"unknown workload {workload!r}; expected one of {', '.join(WORKLOADS)}")
    props = scene.hybrid_raycast
    kinds, notes = candidate_kinds(props)
    cal, cal_message, _ = load_calibration()
    yield 0.01, "preparing the rays"
    depsgraph = evaluated_depsgraph(scene, view_layer)
    vl = view_layer if view_layer is not None else depsgraph.view_layer
    if workload == "CAMERA":
        rays = passes.camera_workload(scene, depsgraph)
        ob = None
    else:
        ob = passes.ao_target(scene, vl, target)
    yield 0.05, "extracting the evaluated triangles"
    s = session.get(depsgraph, props)
    before = s.fingerprint
    grid_config = {"density": float(props.grid_density)}
    mesh, summary, grid = s.mesh, s.summary, s.cached("grid", **grid_config)
    if workload == "AO":
        lo, hi = mesh.bounds()
        rays = passes.ao_workload(ob, depsgraph, props.ao_samples, props.ao_distance,
                                  float(np.linalg.norm(hi.astype(np.float64) - lo)), seed=seed)
        if rays["note"]:
            notes.append(rays["note"])
    m = len(rays["origins"])
    job.fraction, job.text = 0.1, f"planning for {m:,} rays"
    plan = yield from job.call(
        core.plan, mesh, m, cal, rays=(rays["origins"], rays["directions"], rays["tmin"], rays["tmax"]),
        samples=props.sample_rays, grid=grid, grid_config=grid_config, kinds=kinds,
    )
    s.keep(plan.grid, **grid_config)
    grid_build = 0.0 if grid is not None else plan.grid_build_time
    kind = plan.chosen
    config = plan.configs.get(kind, {})
    if kind == "grid":
        acc, build_time = plan.grid, grid_build
    elif s.cached(kind, **config) is not None:
        acc, build_time = s.cached(kind, **config), 0.0
    else:
        job.fraction, job.text = 0.3, f"building the {kind} over {mesh.triangle_count:,} triangles"
        acc = yield from job.call(core.build, mesh, kind, **config)
        build_time = acc.build_time
        s.keep(acc, **config)
    job.fraction = 0.5
    out, trace_time, traced = yield from job.call(_trace_all, job, acc, rays, workload == "AO", plan)
    job.check()
    return {"workload": workload, "rays": rays, "result": out, "plan": plan, "mesh": mesh, "summary": summary,
            "structure": kind, "build_time": build_time, "trace_time": trace_time, "traced": traced,
            "before": before, "view_layer": vl, "object": ob,
            "notes": notes, "calibration_measured": cal.source == "measured", "calibration_message": cal_message}


def apply_trace(scene, result) -> list[tuple[str, str]]:
    """Write the trace's output into Blender; the messages to report."""
    props = scene.hybrid_raycast
    rays, plan, m = result["rays"], result["plan"], len(result["rays"]["origins"])
    if result["workload"] == "CAMERA":
        images = passes.write_pass_images(result["mesh"], passes.pass_images(result["mesh"], result["result"], rays))
        output = ", ".join(i.name for i in images)
        what = f"{rays['width']}x{rays['height']} camera rays"
        hit_share = float(result["result"].hit.mean()) if m else 0.0
        tail = f"; {hit_share * 100:.0f} % hit; images {output}"
    else:
        ob = result["object"]
        attr, ao = passes.write_ao(ob, result["result"], rays["samples"], props.ao_attribute)
        output = f"{ob.name}: {attr.name}"
        what = f"AO rays ({rays['vertices']:,} vertices x {rays['samples']} samples)"
        tail = f"; mean AO {float(ao.mean()):.2f} in attribute '{attr.name}' of '{ob.name}'"
        # our own write: the colour attribute changes no triangle
        session.adopt_own_write(scene, result["view_layer"], result["before"])
    props.trace_workload = result["workload"]
    props.trace_structure = result["structure"].upper()
    props.trace_rays = m
    props.trace_build_time = result["build_time"]
    props.trace_time = result["trace_time"]
    props.trace_output = output
    msgs = [("WARNING", n) for n in result["notes"]]
    if not result["calibration_measured"]:
        msgs.append(("WARNING", result["calibration_message"]))
    built = f", built in {result['build_time'] * 1e3:.0f} ms" if result["build_time"] else ""
    traced = result["traced"]
    early = f" ({m - traced:,} of them answered while planning)" if traced < m else ""
    rate = f" ({traced / max(result['trace_time'], 1e-9):,.0f} rays/s)" if traced else ""
    msgs.append(("INFO", f"traced {m:,} {what}{early} with {plan.decision}{built}, in {result['trace_time']:.2f} s"
                         f"{rate}{tail}"))
    return msgs


class HYBRID_RAYCAST_OT_trace(JobOperator, bpy.types.Operator):
    """Trace a workload with the structure the plan picks for its ray count: camera passes (depth, normal, object ID) or an ambient-occlusion bake"""

    bl_idname = "hybrid_raycast.trace"
    bl_label = "Trace"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Hybrid RT trace"

    workload: bpy.props.EnumProperty(
        name="Workload",
        description="What to shoot",
        items=(
            ("CAMERA", "Camera Passes", "One ray per pixel of the active camera: depth, normal and object-ID images"),
            ("AO", "Bake AO", "Ambient occlusion of the active mesh into a colour attribute"),
        ),
        default="CAMERA",
    )

    @classmethod
    def description(cls, context, properties):
        if properties.workload == "AO":
            return "Bake ambient occlusion of the active mesh into a colour attribute, with the structure the plan picks"
        return "Trace the active camera's pixels into depth, normal and object-ID images, with the structure the plan picks"

    def start(self, context, job):
        return trace_job(context.scene, job, workload=self.workload, view_layer=context.view_layer)

    def finish(self, context, result):
        return apply_trace(context.scene, result)
