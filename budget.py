"""The ray budget: how many rays the user is about to shoot.

'RENDER': render width x height (times the resolution percentage, squared) x samples per
pixel x the expected path length (rays per camera sample: the camera ray, its bounces
and shadow rays).  Samples come from the render engine: Cycles ``cycles.samples``, EEVEE
``eevee.taa_render_samples``, Workbench its anti-aliasing samples, any other engine 1.
'CUSTOM': the number typed in ``custom_rays``.
"""

from __future__ import annotations


def render_samples(scene) -> tuple[int, str]:
    """(samples per pixel, where the number comes from)."""
    engine = scene.render.engine
    if engine == "CYCLES" and hasattr(scene, "cycles"):
        return int(scene.cycles.samples), "Cycles render samples"
    if engine.startswith("BLENDER_EEVEE") and hasattr(scene, "eevee"):
        return int(scene.eevee.taa_render_samples), "EEVEE render samples"
    if engine == "BLENDER_WORKBENCH":
        aa = getattr(scene.display, "render_aa", "OFF")
        return (int(aa) if str(aa).isdigit() else 1), "Workbench anti-aliasing samples"
    return 1, f"{engine} (no sample count: 1)"


def render_rays(scene, path_length: float) -> dict:
    r = scene.render
    pct = r.resolution_percentage / 100.0
    width = max(1, int(r.resolution_x * pct))
    height = max(1, int(r.resolution_y * pct))
    samples, where = render_samples(scene)
    return {
        "width": width,
        "height": height,
        "resolution_percentage": int(r.resolution_percentage),
        "pixels": width * height,
        "samples": samples,
        "samples_from": where,
        "path_length": float(path_length),
        "rays": float(width * height * max(samples, 0) * path_length),
    }


def ray_budget(scene, props) -> dict:
    """Every factor of the budget and the resulting ``rays`` (a float: it can pass 2**31)."""
    d = render_rays(scene, props.path_length)
    d["source"] = props.ray_budget
    if props.ray_budget == "CUSTOM":
        d["rays"] = float(props.custom_rays)
    return d
