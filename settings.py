"""Scene settings and results: ``scene.hybrid_raycast``, and the running job's status.

The one module both sides share: ``operators/`` write here, ``ui/`` draws from here
(imports run ui -> settings <- operators -> core).

Scripts read the results directly, e.g.::

    props = bpy.context.scene.hybrid_raycast
    bpy.ops.hybrid_raycast.analyze()
    props.decision           # 'GRID', 'BVH' or 'EMBREE' ('NONE' before any analysis)
    props.break_even_rays    # rays up to which the grid is cheapest
    props.stale              # the scene or the settings changed since the analysis

Infinite break-evens: Blender stores FloatProperty values as float32, which has no room
for "never".  When the grid is always cheapest, ``break_even_infinite`` is True and
``break_even_rays`` holds ``BREAK_EVEN_NEVER`` (the largest float32, 3.4e38), so
``expected_rays <= break_even_rays`` still reads right.  The same holds for the interval
ends (``break_even_low_infinite``, ``break_even_high_infinite``).  The JSON writes null.

``expected_rays`` is the budget in use: from the render settings when ``ray_budget`` is
'RENDER', else ``custom_rays``.  Assigning it stores the number in ``custom_rays`` and
switches ``ray_budget`` to 'CUSTOM'.
"""

import json
import math

import bpy
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    StringProperty,
)

from .budget import ray_budget, render_samples
from .core.decide.measurements import SCALE_NOTES
from .core.plan import DEFAULT_SAMPLES

#: what ``break_even_rays`` holds when the break-even is infinite (float32's largest value)
BREAK_EVEN_NEVER = 3.4028234663852886e38
#: the largest expected ray count the settings store (custom_rays, expected_rays)
RAYS_MAX = 1.0e15

DECISION_ITEMS = (
    ("NONE", "None", "No analysis yet"),
    ("GRID", "Grid", "Keep the uniform grid: it is cheapest for the expected rays"),
    ("BVH", "BVH", "Build the numpy BVH: it pays for its build within the expected rays"),
    ("EMBREE", "Embree", "Build Embree's BVH (embreex): it pays for its build within the expected rays"),
)


#: what the panel shows while a modal job runs: {"label", "fraction", "text"}; empty when
#: idle.  Written only by ``operators/jobs.py``'s ``JobOperator``; one job runs at a time.
RUNNING: dict = {}

#: how each scene's latest call was traced after the scene changed, per part (its kind, form,
#: triangles and the rule's choice over its life: ``Session.describe``), keyed by the scene's
#: name; written by ``operators/session.py`` when a session builds its parts, drawn by the
#: panel's "Structures per Part".  Empty until a changed scene has been traced.
PARTS: dict = {}

#: each scene's latest closest-point query with the decision for point queries: its structure,
#: points, estimated break-even and reason (``core.decide.points.PointPlan.to_dict`` plus
#: 'points'), keyed by the scene's name; written by ``operators/query.py``, drawn by the
#: panel's "Closest Points".  Empty until a script asks for closest points.
POINTS: dict = {}


def _get_expected(self):
    return min(ray_budget(self.id_data, self)["rays"], RAYS_MAX)


def _set_expected(self, value):
    self.custom_rays = value
    self.ray_budget = "CUSTOM"


def _get_render_samples(self):
    return render_samples(self.id_data)[0]


def current_settings(props) -> dict:
    """The settings an analysis depends on (compared to decide whether it is stale)."""
    return {
        "expected_rays": float(props.expected_rays),
        "selected_only": bool(props.selected_only),
        "candidates": sorted(props.candidates),
        "sample_rays": int(props.sample_rays),
        "grid_density": round(float(props.grid_density), 6),
    }


def stale_reason(props) -> str:
    """Why the results no longer describe the scene ('' when they do, or when there are none)."""
    if not props.has_results:
        return ""
    if props.geometry_changed:
        return "the scene changed since the analysis"
    try:
        then = json.loads(props.analyzed_settings)
    except ValueError:
        return "the analysis settings are unknown"
    now = current_settings(props)
    diff = []
    for key, value in now.items():
        old = then.get(key)
        if key == "expected_rays":
            if old is None or not math.isclose(value, old, rel_tol=1e-6):
                diff.append("expected rays")
        elif value != old:
            diff.append(key.replace("_", " "))
    return f"{', '.join(diff)} changed since the analysis" if diff else ""


def figures_from_props(props) -> dict:
    """What ``core.plot.plot_rgba`` draws, from these properties (None before any analysis)."""
    if not props.has_results:
        return None
    cands = {}
    if props.bvh_considered:
        cands["bvh"] = (props.bvh_build_time, props.bvh_per_ray)
    if props.embree_considered:
        cands["embree"] = (props.embree_build_time, props.embree_per_ray)
    return {
        "grid_per_ray": props.grid_per_ray,
        "candidates": cands,
        "expected_rays": props.analyzed_rays,
        "decision": props.decision,
        "break_even": None if props.break_even_infinite else props.break_even_rays,
        "break_even_low": None if props.break_even_low_infinite else props.break_even_low,
        "break_even_high": None if props.break_even_high_infinite else props.break_even_high,
    }


def _get_stale(self):
    return bool(stale_reason(self))


def _get_stale_reason(self):
    return stale_reason(self)


def _time(name, description, **kw):
    return FloatProperty(name=name, description=description, unit="TIME_ABSOLUTE", subtype="TIME_ABSOLUTE",
                         min=0.0, precision=6, **kw)


#: the calibration scales as enum items (the scene setting's, and the Calibrate operator's
#: after its 'Scene Setting'), described by core (``SCALE_NOTES``)
CALIBRATION_SCALES = (("tiny", "Tiny", SCALE_NOTES["tiny"]), ("quick", "Quick", SCALE_NOTES["quick"]),
                      ("default", "Full", SCALE_NOTES["default"]))


class HybridRaycastSettings(bpy.types.PropertyGroup):
    # == settings ======================================================================
    ray_budget: EnumProperty(
        name="Ray Budget",
        description="Where the expected number of rays comes from",
        items=(
            ("RENDER", "Render", "Render resolution x percentage x samples per pixel x expected path length"),
            ("CUSTOM", "Custom", "A number of rays you type"),
        ),
        default="RENDER",
    )
    custom_rays: FloatProperty(
        name="Custom Rays",
        description="Rays you are about to shoot (used when the ray budget is Custom)",
        default=1.0e6, min=0.0, max=RAYS_MAX, soft_max=1.0e10, precision=0, step=100000,
    )
    expected_rays: FloatProperty(
        name="Expected Rays",
        description="Rays you are about to shoot: decides whether a BVH pays for its build. "
                    "From the render settings or the custom number; setting it switches to Custom",
        min=0.0, max=RAYS_MAX, soft_max=1.0e10, precision=0, step=100000,
        get=_get_expected, set=_set_expected,
    )
    path_length: FloatProperty(
        name="Path Length",
        description="Expected rays per camera sample (the camera ray, its bounces and shadow rays), for the Render budget",
        default=3.0, min=1.0, max=1024.0, soft_max=64.0, precision=1,
    )
    render_samples: IntProperty(
        name="Samples",
        description="Samples per pixel of the scene's render engine (read-only; set it in the render properties)",
        get=_get_render_samples,
    )
    candidates: EnumProperty(
        name="Candidates",
        description="Hierarchical structures weighed against the uniform grid",
        items=(
            ("BVH", "BVH", "The numpy BVH of this add-on"),
            ("EMBREE", "Embree", "Intel Embree through embreex (skipped where embreex cannot be imported)"),
        ),
        options={"ENUM_FLAG"},
        default={"BVH", "EMBREE"},
    )
    sample_rays: IntProperty(
        name="Sample Rays",
        description="Representative rays traced through the grid, whose work counts give its time per ray (K in the "
                    "paper); at most 2% of the expected rays (at least 1,024), and none where they would cost more "
                    "than 10% of the rays' trace",
        default=DEFAULT_SAMPLES, min=1, max=1 << 22, soft_min=256, soft_max=1 << 18,
    )
    grid_density: FloatProperty(
        name="Grid Density",
        description="Grid cells per triangle (Cleary and Wyvill's lambda)",
        default=2.0, min=0.01, max=100.0, soft_min=0.25, soft_max=16.0, precision=2,
    )
    selected_only: BoolProperty(
        name="Selected Only",
        description="Extract only the selected objects (and instances whose instancer is selected)",
        default=False,
    )
    ao_samples: IntProperty(
        name="AO Samples",
        description="Hemisphere rays per vertex for the ambient-occlusion bake",
        default=16, min=1, max=4096, soft_max=256,
    )
    ao_distance: FloatProperty(
        name="AO Distance",
        description="Farthest occluder counted by the ambient-occlusion bake (0: unlimited)",
        default=0.0, min=0.0, soft_max=100.0, subtype="DISTANCE", unit="LENGTH",
    )
    ao_attribute: StringProperty(
        name="AO Attribute",
        description="Colour attribute (per vertex) the ambient-occlusion bake writes",
        default="HRC AO", maxlen=63,
    )
    calibration_scale: EnumProperty(
        name="Calibration",
        description="How many procedural scenes and rays the calibration measures",
        items=CALIBRATION_SCALES,
        default="default",
    )

    # == results of the last extraction =================================================
    has_summary: BoolProperty(name="Has Summary", description="An extraction has run in this scene", default=False)
    triangle_count: IntProperty(name="Triangles", description="Triangles extracted from the evaluated scene", min=0)
    object_count: IntProperty(name="Objects", description="Objects and instances that contributed triangles", min=0)
    instance_count: IntProperty(name="Instances", description="Instances among the contributing objects", min=0)
    extraction_time: _time("Extraction Time", "Wall time of the last extraction")
    bounds_min: FloatVectorProperty(name="Bounds Min", description="World-space minimum corner", subtype="XYZ", unit="LENGTH", size=3)
    bounds_max: FloatVectorProperty(name="Bounds Max", description="World-space maximum corner", subtype="XYZ", unit="LENGTH", size=3)

    # == results of the last analysis ===================================================
    has_results: BoolProperty(name="Has Results", description="An analysis has run in this scene", default=False)
    decision: EnumProperty(name="Decision", description="The structure the analysis chose for the expected rays",
                           items=DECISION_ITEMS, default="NONE")
    decision_certain: BoolProperty(
        name="Certain", description="The expected rays lie outside the break-even interval, so the choice holds "
                                    "at both ends of the calibration's spread", default=False)
    analyzed_rays: FloatProperty(name="Analyzed Rays", description="Expected rays the analysis decided for",
                                 min=0.0, max=RAYS_MAX, precision=0)
    break_even_rays: FloatProperty(
        name="Break-even Rays", description="Rays up to which the already built grid is cheapest "
                                           "(3.4e38 with Break-even Infinite set: the grid always wins)",
        min=0.0, max=BREAK_EVEN_NEVER, precision=0)
    break_even_low: FloatProperty(name="Break-even Low", description="Low end of the break-even interval "
                                  "(the calibration's cheap-build, fast-ray end)", min=0.0, max=BREAK_EVEN_NEVER, precision=0)
    break_even_high: FloatProperty(name="Break-even High", description="High end of the break-even interval "
                                   "(the calibration's dear-build, slow-ray end)", min=0.0, max=BREAK_EVEN_NEVER, precision=0)
    break_even_infinite: BoolProperty(name="Break-even Infinite", description="No candidate ever beats the grid")
    break_even_low_infinite: BoolProperty(name="Break-even Low Infinite", description="The interval's low end is infinite")
    break_even_high_infinite: BoolProperty(name="Break-even High Infinite", description="The interval's high end is infinite")
    break_even_kind: EnumProperty(
        name="Break-even Against", description="The candidate that first beats the grid",
        items=(("NONE", "None", "No candidate beats the grid"), ("BVH", "BVH", ""), ("EMBREE", "Embree", "")),
        default="NONE")
    grid_build_time: _time("Grid Build", "Measured build time of the uniform grid")
    break_even_warning: StringProperty(
        name="Break-even Warning", description="Why the break-even estimate is ill-conditioned (empty when it "
        "is not): the grid and the candidate that attains it are close per ray, so a small error in either moves it "
        "far")
    grid_built: BoolProperty(
        name="Grid Built", default=True,
        description="Whether the analysis built the grid: not when the calibration alone settled the decision "
        "(the expected rays above its ceiling on the break-even against a structure much faster per ray)")
    break_even_ceiling: FloatProperty(
        name="Break-even Ceiling", description="The rays from which the calibration alone settled the decision: "
        "its upper bound on the break-even against the structure it settled for, or where Settled Slack is above 0 "
        "the rays from which building that structure costs at most that much more than the grid (0 when the "
        "analysis measured the grid)", min=0.0, max=BREAK_EVEN_NEVER, precision=0)
    settled_slack: FloatProperty(
        name="Settled Slack", description="How much more than the grid, at most, building the settled structure may "
        "cost on the calibration's estimates (a surface mesh, decided without a sample); 0 when the structure "
        "beats the grid on the calibration's bounds or the analysis measured the grid", min=0.0, max=1.0,
        subtype="FACTOR", precision=2)
    grid_per_ray: _time("Grid per Ray", "Grid time per ray on a large workload: from the sample rays' work counts "
                        "(traversal steps and candidate triangles, or cells with an older calibration) with the "
                        "calibrated count model, or else their measured time times the calibrated batch ratio")
    grid_cells_per_ray: FloatProperty(
        name="Cells per Ray", description="Grid cells a sample ray steps through, on average (0 when the estimate "
        "came from the sample's time instead of its work counts)", min=0.0, precision=1)
    grid_steps_per_ray: FloatProperty(
        name="Steps per Ray", description="Steps the grid's traversal took per sample ray, on average: a jump over "
        "empty space is one step (0 when the sample's traversal was not counted or the grid's count model, an "
        "older calibration's, weighs cells instead)", min=0.0, precision=1)
    grid_candidates_per_ray: FloatProperty(
        name="Candidates per Ray", description="Triangle references in the cells the traversal stopped in, per "
        "sample ray, on average (0 when the sample's traversal was not counted or the grid's count model does not "
        "weigh them)", min=0.0, precision=1)
    grid_refs_per_ray: FloatProperty(
        name="References per Ray", description="Triangle references in those cells, on average (0 when the estimate "
        "came from the sample's time or no count model weighs references, so they were not counted)", min=0.0, precision=1)
    samples_traced: IntProperty(name="Samples Traced", description="Sample rays the grid's time per ray comes from", min=0)
    no_sample_reason: StringProperty(
        name="No Sample", description="Why the analysis traced no sample rays (empty when it did): too few rays for "
        "any structure to pay back its build, or a sample that would cost more than a tenth of the rays' trace")
    grid_sample_ratio: FloatProperty(
        name="Batch Ratio", description="Calibrated ratio of the grid's time per ray on a large workload to its time "
        "per ray on this many sample rays (a small batch pays the traversal's fixed costs over few rays)",
        min=0.0, soft_max=2.0, precision=3, default=1.0)
    bvh_considered: BoolProperty(name="BVH Considered", description="The BVH was a candidate with calibration constants")
    bvh_build_time: _time("BVH Build (est.)", "Estimated BVH build time, from the calibration's build model for N triangles")
    bvh_per_ray: _time("BVH per Ray (est.)", "Estimated BVH time per ray, from the calibration's model (the grid sample's counts, or N)")
    embree_considered: BoolProperty(name="Embree Considered", description="Embree was a candidate, importable, with calibration constants")
    embree_available: BoolProperty(name="Embree Available", description="embreex could be imported at the analysis")
    embree_unavailable: StringProperty(name="Embree Unavailable", description="Why Embree could not be used at the analysis (empty when it could)")
    embree_build_time: _time("Embree Build (est.)", "Estimated Embree build time, from the calibration's build model for N triangles")
    embree_per_ray: _time("Embree per Ray (est.)", "Estimated Embree time per ray, from the calibration's model (the grid sample's counts, or N)")
    analyzed_at: StringProperty(name="Analyzed At", description="When the analysis ran (local time, ISO 8601)")
    analysis_duration: _time("Analysis Time", "Wall time of the whole analysis (extraction, grid, samples, plan)")
    calibration_source: StringProperty(name="Calibration", description="Where the calibration constants came from")
    calibration_message: StringProperty(name="Calibration Message", description="How the calibration was loaded")
    notes: StringProperty(name="Notes", description="The plan's notes, separated by ' | '")
    geometry_changed: BoolProperty(
        name="Geometry Changed", description="The scene's geometry, transforms or visibility changed since the analysis",
        default=False)
    analyzed_settings: StringProperty(name="Analyzed Settings", description="The settings of the analysis (JSON)",
                                      options={"HIDDEN"})
    last_analysis_json: StringProperty(name="Last Analysis", description="The last analysis, as the CLI writes it (JSON)",
                                       options={"HIDDEN"})
    stale: BoolProperty(name="Stale", description="The scene or the analysis settings changed since the analysis",
                        get=_get_stale)
    stale_reason: StringProperty(name="Stale Reason", description="What changed since the analysis",
                                 get=_get_stale_reason)

    # == results of the last trace ======================================================
    trace_workload: StringProperty(name="Traced", description="What the last trace shot: 'CAMERA' or 'AO'")
    trace_structure: EnumProperty(name="Traced With", description="The structure the last trace used",
                                  items=DECISION_ITEMS, default="NONE")
    trace_rays: FloatProperty(name="Traced Rays", description="Rays the last trace shot", min=0.0, precision=0)
    trace_build_time: _time("Trace Build", "Time the last trace spent building its structure (0 when reused)")
    trace_time: _time("Trace Time", "Time the last trace spent tracing")
    trace_output: StringProperty(name="Trace Output", description="What the last trace wrote (images or attribute)")
