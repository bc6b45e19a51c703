"""The main job: analyze and trace the built-in demo scene headless.

    make demo            (or: .venv/bin/python scripts/demo.py --output out/demo)

Builds the demo scene in Blender-as-a-module with the add-on registered, then runs the
same code as ``blender -b -c hybrid_raycast analyze|trace``: extract, build the grid,
time sample rays, decide for the scene's ray budget (render resolution x samples x path
length), and trace the camera passes with the structure the plan picks for them.
Prints the decision and writes into the output folder:

    demo.json                      every figure of the analysis and the trace
    hybrid_raycast_depth.png       the depth pass (near white, far black)
    hybrid_raycast_normal.png      the normal pass
    hybrid_raycast_object_id.png   the object-id pass
    hybrid_raycast_plot.png        total time versus rays, grid and candidates
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import load_addon  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output", type=Path, default=Path("out/demo"), help="folder for the JSON and the pictures (created)")
    ap.add_argument("--subdivision", type=int, default=2, help="subdivision levels of the demo Suzanne (0-5)")
    ap.add_argument("--rays", type=float, default=None, help="expected rays (default: the render budget)")
    args = ap.parse_args(argv)

    import bpy  # noqa: F401  (Blender as a module)

    addon = load_addon()
    from hybrid_raycast.operators import cli
    from hybrid_raycast.operators.demo_scene import build_demo_scene

    addon.register()
    try:
        scene = build_demo_scene(subdivision_levels=args.subdivision)
        out = args.output
        cli_args = ["--output", str(out)] + (["--rays", str(args.rays)] if args.rays else [])
        print(f"Hybrid Ray Cast demo: scene '{scene.name}'")
        code = cli.main(["analyze", *cli_args])
        if code == 0:
            code = cli.main(["trace", *cli_args, "--json", str(out / "demo.json")])
        if code != 0:
            print(f"demo failed (exit code {code})", file=sys.stderr)
            return code
        doc = json.loads((out / "demo.json").read_text())
    finally:
        addon.unregister()

    s, b, be = doc["summary"], doc["budget"], doc["break_even"]
    print()
    print(f"  scene        {s['triangles']:,} triangles, {s['objects']} objects ({s['instances']} instances)")
    print(f"  ray budget   {b['width']}x{b['height']} px x {b['samples']} samples x path length {b['path_length']:g}"
          f" = {doc['expected_rays']:,.0f} rays" if b["source"] == "RENDER" else
          f"  ray budget   {doc['expected_rays']:,.0f} rays (custom)")
    def n(x):
        return "never" if x is None else f"{x:,.0f}"

    print(f"  break-even   {n(be['rays'])} rays [{n(be['low'])}, {n(be['high'])}]"
          + (f" against {be['against']}" if be["against"] else " (the grid always wins)"))
    print(f"  calibration  {doc['calibration']['source']}")
    print(f"  DECISION     {doc['decision']} for {doc['expected_rays']:,.0f} rays"
          f"{'' if doc['certain'] else ' (uncertain: inside the interval)'}")
    t = doc["trace"]
    print(f"  trace        {t['rays']:,} camera rays with {t['structure'].upper()}: "
          f"build {t['build_time'] * 1e3:.0f} ms, trace {t['trace_time']:.2f} s")
    for name, path in doc.get("files", {}).items():
        print(f"  wrote        {path}  ({name})")
    print(f"  wrote        {out / 'demo.json'}")
    return 0


if __name__ == "__main__":
    from _bpy_exit import exit_past_bpy

    code = main()
    exit_past_bpy(code)
    sys.exit(code)
