"""The 3D View sidebar tab "Hybrid RT": draws scene.hybrid_raycast and calls operators.

Main panel: the ray budget, Analyze, the decision in large type, the break-even count
with its interval against the expected rays, the time-versus-rays plot and the
stale-results hint.  Sub-panels: the scene and per-structure figures, the settings,
and tracing (camera passes, AO bake).  Everything drawn here is also a property of
``scene.hybrid_raycast`` and a field of the CLI's JSON.
"""

import bpy

from ..settings import PARTS, POINTS, RUNNING, figures_from_props
from . import plot


def _rays(x: float) -> str:
    if x >= 1e9:
        return f"{x / 1e9:.3g}G"
    if x >= 1e6:
        return f"{x / 1e6:.3g}M"
    if x >= 1e3:
        return f"{x / 1e3:.3g}k"
    return f"{x:.0f}"


def _secs(x: float) -> str:
    if x >= 1.0:
        return f"{x:.2f} s"
    if x >= 1e-3:
        return f"{x * 1e3:.1f} ms"
    if x >= 1e-6:
        return f"{x * 1e6:.2f} us"
    return f"{x * 1e9:.1f} ns"


def _kind_name(kind: str) -> str:
    """'BVH', 'Embree' for the settings' enum names."""
    return kind if kind == "BVH" else kind.capitalize()


def break_even_text(props) -> tuple[str, str]:
    """(point, interval) as the panel shows them."""
    if not props.grid_built:  # settled by the calibration alone: no grid to keep
        kind = _kind_name(props.break_even_kind)
        if props.settled_slack > 0:
            hi = "inf" if props.break_even_high_infinite else _rays(props.break_even_high)
            return (f"{_rays(props.break_even_rays)} rays on the calibration alone (no grid built)",
                    f"[{_rays(props.break_even_low)} - {hi}], the calibration's")
        if props.break_even_ceiling <= 0:
            return f"none: {kind} from the first ray (no grid built)", "the calibration's"
        return (f"at most {_rays(props.break_even_ceiling)} rays (no grid built)",
                f"[{_rays(props.break_even_low)} - {_rays(props.break_even_high)}], the calibration's")
    point = "never (the grid always wins)" if props.break_even_infinite else f"{_rays(props.break_even_rays)} rays"
    lo = "inf" if props.break_even_low_infinite else _rays(props.break_even_low)
    hi = "inf" if props.break_even_high_infinite else _rays(props.break_even_high)
    return point, f"[{lo} - {hi}]"


class _Base:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Hybrid RT"


class VIEW3D_PT_hybrid_raycast(_Base, bpy.types.Panel):
    bl_label = "Hybrid Ray Cast"

    def draw(self, context):
        layout = self.layout
        scene = context.scene
        props = scene.hybrid_raycast

        # -- the ray budget ---------------------------------------------------------
        col = layout.column(align=True)
        col.row(align=True).prop(props, "ray_budget", expand=True)
        if props.ray_budget == "RENDER":
            r = scene.render
            pct = r.resolution_percentage / 100
            box = col.box()
            sub = box.column(align=True)
            sub.label(text=f"{int(r.resolution_x * pct)} x {int(r.resolution_y * pct)} px ({r.resolution_percentage} %)",
                      icon="RESTRICT_RENDER_OFF")
            sub.label(text=f"x {props.render_samples} samples")
            sub.prop(props, "path_length", text="x Path Length")
            sub.label(text=f"= {_rays(props.expected_rays)} rays")
        else:
            col.prop(props, "custom_rays", text="Rays")

        # -- run ---------------------------------------------------------------------
        if RUNNING:
            box = layout.box()
            text = f"{RUNNING.get('label', '')}: {RUNNING.get('text', '')}"
            if hasattr(box, "progress"):
                box.progress(factor=float(RUNNING.get("fraction", 0.0)), type="BAR", text=text)
            else:
                box.label(text=text, icon="TIME")
            box.label(text="Esc cancels", icon="CANCEL")
        row = layout.row(align=True)
        row.scale_y = 1.5
        row.operator("hybrid_raycast.analyze", icon="VIEWZOOM")
        row.operator("hybrid_raycast.calibrate", text="", icon="PREFERENCES")

        if not props.has_results:
            layout.label(text="Analyze to decide: grid or BVH?", icon="INFO")
            return

        # -- the decision --------------------------------------------------------------
        if props.stale:
            warn = layout.box()
            warn.alert = True
            warn.label(text="Results are stale:", icon="ERROR")
            warn.label(text=props.stale_reason)
        box = layout.box()
        big = box.row()
        big.scale_y = 2.2
        big.alignment = "CENTER"
        big.label(text=props.decision, icon="CHECKMARK" if props.decision_certain else "QUESTION")
        point, interval = break_even_text(props)
        sub = box.column(align=True)
        sub.label(text=f"Expected: {_rays(props.analyzed_rays)} rays")
        sub.label(text=f"Break-even: {point}")
        sub.label(text=f"Interval: {interval}")
        if not props.decision_certain:
            sub.label(text="Expected rays inside the interval: uncertain", icon="QUESTION")
        if props.break_even_warning:  # "ill-conditioned: the grid is only ..., so a 10% error ...; near it ..."
            head, _, rest = props.break_even_warning.partition(", so ")
            sub.label(text=head[0].upper() + head[1:], icon="INFO")
            sub.label(text="  so " + rest.split(";")[0])

        icon = plot.panel_preview(scene.name, figures_from_props(props))
        if icon:
            layout.template_icon(icon_value=icon, scale=10.0)
            legend = layout.row(align=True)
            legend.label(text="Grid", icon="KEYTYPE_KEYFRAME_VEC")
            if props.bvh_considered:
                legend.label(text="BVH", icon="KEYTYPE_BREAKDOWN_VEC")
            if props.embree_considered:
                legend.label(text="Embree", icon="KEYTYPE_JITTER_VEC")
            layout.label(text="Total time vs rays (log-log); band: interval")
        layout.label(text=f"Calibration: {props.calibration_source}", icon="PREFERENCES")
        if not props.embree_available:
            layout.label(text=f"Embree unavailable: {props.embree_unavailable or 'embreex not importable'}", icon="INFO")


class VIEW3D_PT_hybrid_raycast_figures(_Base, bpy.types.Panel):
    bl_label = "Scene and Timings"
    bl_parent_id = "VIEW3D_PT_hybrid_raycast"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        props = context.scene.hybrid_raycast
        if not props.has_summary:
            layout.label(text="No analysis yet")
            return
        col = layout.column(align=True)
        col.label(text=f"{props.triangle_count:,} triangles", icon="MESH_DATA")
        col.label(text=f"{props.object_count:,} objects ({props.instance_count:,} instances)", icon="OBJECT_DATA")
        lo, hi = props.bounds_min, props.bounds_max
        col.label(text="Size {:.3g} x {:.3g} x {:.3g}".format(*(h - l for l, h in zip(lo, hi))))
        col.label(text=f"Extracted in {_secs(props.extraction_time)}", icon="TIME")
        if not props.has_results:
            return
        col = layout.column(align=True)
        if not props.grid_built:
            kind = ("the " if props.break_even_kind == "BVH" else "") + _kind_name(props.break_even_kind)
            col.label(text="Grid: not built")
            if props.settled_slack > 0:
                col.label(text=f"  (above {props.break_even_ceiling:,.0f} rays {kind} costs at most "
                               f"{props.settled_slack:.0%} more than the grid on the calibration alone)")
            elif props.break_even_ceiling > 0:
                col.label(text=f"  (above {props.break_even_ceiling:,.0f} rays {kind} wins on the calibration alone)")
            else:
                col.label(text=f"  ({kind} built faster and traced faster on every calibration scene)")
        else:
            col.label(text=f"Grid: build {_secs(props.grid_build_time)}, {_secs(props.grid_per_ray)}/ray")
            if props.samples_traced == 0:
                col.label(text=f"  (no sample: {props.no_sample_reason or 'too few rays for any structure to pay back its build'})")
            elif props.grid_steps_per_ray > 0:
                col.label(text=f"  (work counts of {props.samples_traced:,} sample rays: {props.grid_steps_per_ray:.1f} "
                               f"steps, {props.grid_candidates_per_ray:.1f} candidates/ray)")
            elif props.grid_cells_per_ray > 0:
                refs = f", {props.grid_refs_per_ray:.1f} refs" if props.grid_refs_per_ray > 0 else ""
                col.label(text=f"  (work counts of {props.samples_traced:,} sample rays: "
                               f"{props.grid_cells_per_ray:.1f} cells{refs}/ray)")
            else:
                col.label(text=f"  (from {props.samples_traced:,} sample rays x {props.grid_sample_ratio:.2f} batch ratio)")
        if props.bvh_considered:
            col.label(text=f"BVH (est.): build {_secs(props.bvh_build_time)}, {_secs(props.bvh_per_ray)}/ray")
        if props.embree_considered:
            col.label(text=f"Embree (est.): build {_secs(props.embree_build_time)}, {_secs(props.embree_per_ray)}/ray")
        elif not props.embree_available:
            col.label(text="Embree: embreex not importable", icon="INFO")
        col.label(text=f"Analyzed {props.analyzed_at} in {_secs(props.analysis_duration)}", icon="TIME")
        if props.notes:
            for note in props.notes.split(" | "):
                col.label(text=note)


def part_lines(described: dict) -> list[tuple[str, str]]:
    """(text, icon) lines of a scene's parts (``Session.describe``): each part's structure,
    form and size, and for a part that chose by the rule over its life, the rays it expects,
    why, and from how many rays a structure beats the grid."""
    names = {"grid": "Grid", "bvh": "BVH", "embree": "Embree", "mixed": "Mixed"}
    out = []

    def choice(c, indent):
        be = c.get("break_even")
        tail = "" if c.get("break_even_kind") is None else (
            f"; {names.get(c['break_even_kind'], c['break_even_kind'])} beats the grid "
            + ("never" if be is None else "at once" if be == 0 else f"from {_rays(be)} rays"))
        out.append((f"{indent}{names.get(c['kind'], c['kind'])}: {_rays(c['rays_expected'])} rays over its life{tail}",
                    "BLANK1"))
        out.append((f"{indent}  ({c['life']})", "BLANK1"))

    for p in described.get("parts", ()):
        out.append((f"{names.get(p['kind'], p['kind'])}, {p['form']}: {p['placements']:,} placements, "
                    f"{p['triangles']:,} triangles", "MESH_DATA"))
        if "choice" in p:
            choice(p["choice"], "  ")
        for m in p.get("meshes", ()):
            out.append((f"  {m['what']}, {m['triangles']:,} triangles", "BLANK1"))
            choice(m, "    ")
    return out


def _lines_draw(table: dict, empty: str, lines):
    """A closed sub-panel's ``draw``: the (text, icon) lines ``lines(entry)`` of the scene's
    entry in ``table`` (a ``settings`` dict keyed by scene name), or ``empty`` without one."""

    def draw(self, context):
        entry = table.get(context.scene.name)
        if not entry:
            self.layout.label(text=empty, icon="INFO")
            return
        col = self.layout.column(align=True)
        for text, icon in lines(entry):
            col.label(text=text, icon=icon)

    return draw


class VIEW3D_PT_hybrid_raycast_parts(_Base, bpy.types.Panel):
    bl_label = "Structures per Part"
    bl_parent_id = "VIEW3D_PT_hybrid_raycast"
    bl_options = {"DEFAULT_CLOSED"}
    draw = _lines_draw(PARTS, "One flat structure until the scene changes between calls", part_lines)


def point_lines(plan: dict) -> list[tuple[str, str]]:
    """(text, icon) lines of a scene's latest closest-point decision (``settings.POINTS``)."""
    names = {"grid": "Grid", "bvh": "BVH"}
    be = plan.get("break_even")
    out = [(f"{names.get(plan['kind'], plan['kind'])} for {plan['points']:,} points, {plan['triangles']:,} triangles",
            "CHECKMARK")]
    if plan.get("estimates"):
        out.append(("BVH beats the grid " + ("never" if be is None else "at once" if be == 0 else
                                             f"from {be:,.0f} points"), "BLANK1"))
        out.append((f"Grid sample: {plan['sample']:,} points", "BLANK1"))
    if plan.get("handed_over"):
        out.append((f"{plan['handed_over']:,} points too far for the grid: the BVH answered them", "BLANK1"))
    out.append((f"({plan['reason']})", "BLANK1"))
    return out


class VIEW3D_PT_hybrid_raycast_points(_Base, bpy.types.Panel):
    bl_label = "Closest Points"
    bl_parent_id = "VIEW3D_PT_hybrid_raycast"
    bl_options = {"DEFAULT_CLOSED"}
    draw = _lines_draw(POINTS, "No closest-point query yet (api.closest)", point_lines)


class VIEW3D_PT_hybrid_raycast_settings(_Base, bpy.types.Panel):
    bl_label = "Settings"
    bl_parent_id = "VIEW3D_PT_hybrid_raycast"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        props = context.scene.hybrid_raycast
        layout.prop(props, "candidates")
        layout.prop(props, "sample_rays")
        layout.prop(props, "grid_density")
        layout.prop(props, "selected_only")
        layout.prop(props, "calibration_scale")


class VIEW3D_PT_hybrid_raycast_trace(_Base, bpy.types.Panel):
    bl_label = "Trace"
    bl_parent_id = "VIEW3D_PT_hybrid_raycast"

    def draw(self, context):
        layout = self.layout
        props = context.scene.hybrid_raycast
        layout.operator("hybrid_raycast.trace", text="Camera Passes", icon="RENDER_STILL").workload = "CAMERA"
        col = layout.column(align=True)
        col.prop(props, "ao_samples")
        col.prop(props, "ao_distance")
        col.prop(props, "ao_attribute", text="")
        col.operator("hybrid_raycast.trace", text="Bake AO", icon="SHADING_RENDERED").workload = "AO"
        layout.operator("hybrid_raycast.bake_proximity", icon="DRIVER_DISTANCE")
        if props.trace_structure != "NONE":
            box = layout.box()
            box.label(text=f"{_rays(props.trace_rays)} {props.trace_workload.lower()} rays with {props.trace_structure}")
            box.label(text=f"build {_secs(props.trace_build_time)}, trace {_secs(props.trace_time)}")
            box.label(text=props.trace_output)
