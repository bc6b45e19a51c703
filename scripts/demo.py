"""The main job: a headless run on the built-in demo scene.

    make demo            (or: .venv/bin/python scripts/demo.py --output out/demo)

Builds the demo scene in Blender-as-a-module, extracts its evaluated triangles and
prints the scene summary; writes it as JSON into the output folder.
"""

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _package import load_addon  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output", type=Path, default=Path("out/demo"), help="folder for demo.json (created)")
    ap.add_argument("--subdivision", type=int, default=2, help="subdivision levels of the demo Suzanne (0-5)")
    args = ap.parse_args(argv)

    import bpy

    addon = load_addon()
    from hybrid_raycast.operators.demo_scene import build_demo_scene
    from hybrid_raycast.operators.extract import scene_mesh, scene_summary

    addon.register()
    try:
        build_demo_scene(subdivision_levels=args.subdivision)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        t0 = time.perf_counter()
        mesh = scene_mesh(depsgraph)
        summary = scene_summary(depsgraph, mesh, time.perf_counter() - t0)
    finally:
        addon.unregister()

    print(f"Hybrid Ray Cast demo scene: {bpy.context.scene.name}")
    width = max(len(k) for k in summary)
    for key, value in summary.items():
        print(f"  {key:<{width}}  {value}")
    args.output.mkdir(parents=True, exist_ok=True)
    out = args.output / "demo.json"
    out.write_text(json.dumps({"summary": summary}, indent=2, default=str))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
