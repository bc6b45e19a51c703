"""HYBRID_RAYCAST_OT_analyze: extract the scene, build the grid, time sample rays, decide.

The analysis is Hapala et al.'s application step (``core.plan``) on the evaluated scene
with the ray budget of ``scene.hybrid_raycast``.  Its outcome is one JSON-able *record*
(``analysis_record``): every figure the sidebar shows, and ``core.Plan.to_dict()`` in
full.  ``store_results`` copies the record into the scene properties and keeps the JSON
in ``last_analysis_json``; ``results_json`` is what the CLI writes.
"""

from __future__ import annotations

import json
import math
import time
from datetime import datetime

import bpy

from .. import core
from ..budget import ray_budget
from ..settings import BREAK_EVEN_NEVER as NEVER
from . import session
from .calibrate import load_calibration
from .jobs import BadInput, Job, JobOperator
from .session import evaluated as evaluated_depsgraph
from .session import extract  # noqa: F401  (operators.analyze.extract: the extraction with one-line errors)
from .summary import store_summary

RECORD_FORMAT = 1


def candidate_kinds(props) -> tuple[tuple[str, ...], list[str]]:
    """('grid', chosen candidates that can be built here), notes on the ones skipped."""
    kinds, notes = ["grid"], []
    if "BVH" in props.candidates:
        kinds.append("bvh")
    if "EMBREE" in props.candidates:
        reason = core.embree.embree_unavailable_reason()
        if reason is None:
            kinds.append("embree")
        else:
            rest = "between the grid and the BVH" if "bvh" in kinds else "on the grid alone"
            notes.append(f"Embree unavailable: {reason}; deciding {rest}")
    return tuple(kinds), notes


# -- the record --------------------------------------------------------------------------

def _finite(x):
    return float(x) if x is not None and math.isfinite(x) else None


def analysis_record(scene, summary, budget, settings, calibration_info, plan, *, started, duration, embree_ok) -> dict:
    """Every figure of an analysis, JSON-able (infinite break-evens as null)."""
    cands = plan.candidates
    return {
        "format": RECORD_FORMAT,
        "blender": bpy.app.version_string,
        "file": bpy.data.filepath,
        "scene": scene.name,
        "analyzed_at": started,
        "analysis_seconds": duration,
        "summary": summary,
        "budget": budget,
        "settings": settings,
        "calibration": calibration_info,
        "embree_available": bool(embree_ok),
        "embree_unavailable": None if embree_ok else core.embree.embree_unavailable_reason(),
        "decision": plan.decision,
        "certain": plan.certain,
        "expected_rays": plan.expected_rays,
        "break_even": {
            "rays": _finite(plan.break_even),
            "low": _finite(plan.break_even_low),
            "high": _finite(plan.break_even_high),
            "infinite": not math.isfinite(plan.break_even),
            "against": plan.break_even_kind if math.isfinite(plan.break_even) else None,
        },
        "structures": {
            k: {"build_time": c.build_time, "build_low": c.build_low, "build_high": c.build_high,
                "per_ray": c.per_ray, "per_ray_low": c.per_ray_low, "per_ray_high": c.per_ray_high,
                "measured": c.measured}
            for k, c in cands.items()
        },
        "plan": plan.to_dict(),
        "summary_line": plan.summary(),
    }


def store_results(props, record):
    """Copy an analysis record into ``scene.hybrid_raycast`` (the only place that does)."""
    store_summary(props, record["summary"])
    props.decision = record["decision"]
    props.decision_certain = record["certain"]
    props.analyzed_rays = record["expected_rays"]
    be = record["break_even"]
    for name, key in (("break_even_rays", "rays"), ("break_even_low", "low"), ("break_even_high", "high")):
        value = be[key]
        setattr(props, name, NEVER if value is None else min(value, NEVER))
        setattr(props, name.replace("_rays", "") + "_infinite", value is None)
    props.break_even_kind = (be["against"] or "none").upper()
    st = record["structures"]
    props.grid_build_time = st["grid"]["build_time"]
    props.grid_per_ray = st["grid"]["per_ray"]
    props.samples_traced = record["plan"]["samples"]
    props.no_sample_reason = record["plan"].get("no_sample", "")
    props.grid_built = record["plan"].get("grid_built", True)
    props.break_even_warning = record["plan"].get("ill_conditioned", "")
    props.break_even_ceiling = min(record["plan"].get("break_even_ceiling") or 0.0, NEVER)
    props.settled_slack = record["plan"].get("settled_slack", 0.0)
    props.grid_sample_ratio = record["plan"].get("grid_sample_ratio", 1.0)
    work = record["plan"].get("work") or {}
    # the counts the grid's model weighed (an older calibration weighs cells, not steps):
    # the sidebar quotes those, so a count it shows is one the estimate used
    weighed = set(record["plan"].get("grid_terms") or ())
    props.grid_cells_per_ray = work.get("cells", 0.0)
    for name in ("steps", "candidates"):  # None: a grid that does not count its traversal
        setattr(props, f"grid_{name}_per_ray", (work.get(name) or 0.0) if name in weighed else 0.0)
    props.grid_refs_per_ray = work.get("refs") or 0.0  # None: not counted (no model weighs it)
    for kind in ("bvh", "embree"):
        c = st.get(kind)
        setattr(props, f"{kind}_considered", c is not None)
        setattr(props, f"{kind}_build_time", c["build_time"] if c else 0.0)
        setattr(props, f"{kind}_per_ray", c["per_ray"] if c else 0.0)
    props.embree_available = record["embree_available"]
    props.embree_unavailable = record.get("embree_unavailable") or ""
    props.analyzed_at = record["analyzed_at"]
    props.analysis_duration = record["analysis_seconds"]
    props.calibration_source = record["calibration"]["source"]
    props.calibration_message = record["calibration"]["message"]
    props.notes = " | ".join(record["plan"]["notes"])
    props.analyzed_settings = json.dumps(record["settings"])
    props.last_analysis_json = json.dumps(record)
    props.geometry_changed = False
    props.has_results = True


def results_json(props) -> dict:
    """The last analysis record with the current stale flag and the last trace: the CLI's JSON."""
    if not props.last_analysis_json:
        return {}
    record = json.loads(props.last_analysis_json)
    record["stale"] = bool(props.stale)
    record["stale_reason"] = props.stale_reason
    record["last_trace"] = None
    if props.trace_structure != "NONE":
        record["last_trace"] = {
            "workload": props.trace_workload, "structure": props.trace_structure, "rays": props.trace_rays,
            "build_time": props.trace_build_time, "trace_time": props.trace_time, "output": props.trace_output,
        }
    return record


# -- the job -------------------------------------------------------------------------------

def settings_of(props) -> dict:
    from ..settings import current_settings

    return current_settings(props)


def analysis_job(scene, job: Job, *, view_layer=None):
    """Generator: extract, build the grid, time the sample rays, plan.  Returns a dict
    with the record and the objects to cache; writes nothing into Blender."""
    props = scene.hybrid_raycast
    budget = ray_budget(scene, props)
    expected = budget["rays"]
    if not (expected > 0 and math.isfinite(expected)):
        raise BadInput("expected rays is 0: set a ray budget (Custom rays, or the render resolution and samples)")
    settings = settings_of(props)
    kinds, notes = candidate_kinds(props)
    started = datetime.now().astimezone().isoformat(timespec="seconds")
    t0 = time.perf_counter()
    cal, message, path = load_calibration()
    yield 0.02, "extracting the evaluated triangles"
    depsgraph = evaluated_depsgraph(scene, view_layer)
    s = session.get(depsgraph, props)
    mesh, summary, body = s.mesh, s.summary, s.body
    vl = depsgraph.view_layer
    grid_config = {"density": float(props.grid_density)}
    yield 0.3, f"building the grid over {mesh.triangle_count:,} triangles and tracing {props.sample_rays:,} sample rays"
    job.fraction, job.text = 0.3, f"grid over {mesh.triangle_count:,} triangles, {props.sample_rays:,} sample rays"
    plan = yield from job.call(
        core.plan, mesh, expected, cal, samples=props.sample_rays, grid=s.cached("grid", **grid_config),
        grid_config=grid_config, kinds=kinds,
    )
    plan.notes[:0] = notes
    job.check()
    calibration_info = {"source": cal.source, "message": message, "path": str(path) if path else None,
                        "measured": cal.source == "measured"}
    record = analysis_record(scene, summary, budget, settings, calibration_info, plan, started=started,
                             duration=time.perf_counter() - t0, embree_ok=core.embree.embree_available())
    record["scene_structures"] = s.describe()  # how casts of this scene are traced now (flat, or in parts)
    yield 1.0, "done"
    return {"record": record, "mesh": mesh, "plan": plan, "summary": summary, "session": s, "body": body,
            "grid_config": grid_config, "view_layer": vl, "notes": notes, "calibration": cal}


def apply_analysis(scene, result) -> list[tuple[str, str]]:
    """Write an analysis into the scene (properties, cache); the messages to report."""
    props = scene.hybrid_raycast
    record = result["record"]
    store_results(props, record)
    s = result["session"]
    s.keep(result["plan"].grid, **result["grid_config"])
    s.analysis_plan = result["plan"]
    try:
        depsgraph = evaluated_depsgraph(scene, result["view_layer"])
    except ReferenceError:
        depsgraph = evaluated_depsgraph(scene)
    session.remember_analysis(depsgraph, props.selected_only, result["body"])
    if session.fingerprint(depsgraph, props.selected_only)[1] != result["body"]:  # changed while the job ran
        props.geometry_changed = True
    msgs = []
    cal = record["calibration"]
    if not cal["measured"]:
        msgs.append(("WARNING", cal["message"]))
    for note in result["notes"]:
        msgs.append(("WARNING", note))
    msgs.append(("INFO", record["summary_line"]))
    return msgs


class HYBRID_RAYCAST_OT_analyze(JobOperator, bpy.types.Operator):
    """Extract the scene, build a uniform grid, time sample rays through it and decide whether a BVH pays for itself"""

    bl_idname = "hybrid_raycast.analyze"
    bl_label = "Analyze"
    bl_options = {"REGISTER", "UNDO"}
    job_label = "Hybrid RT analysis"

    def start(self, context, job):
        return analysis_job(context.scene, job, view_layer=context.view_layer)

    def finish(self, context, result):
        return apply_analysis(context.scene, result)
