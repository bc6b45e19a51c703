"""The headless command line: ``blender -b scene.blend -c hybrid_raycast <command> [options]``.

Registered with ``bpy.utils.register_cli_command`` when the add-on is enabled (so the
add-on must be enabled in the preferences Blender starts with).  Blender loads a .blend
given *before* ``-c`` first, then runs the command (checked with Blender 4.3.2); or pass
``--blend PATH`` to open one from the command.

Commands
    analyze    extract, build the grid, time sample rays, decide; JSON of every figure
    trace      the camera passes (or ``--workload ao``: an AO bake of ``--object``) with
               the structure the plan picks; analyzes first when there is no fresh
               analysis, so the JSON holds both; ``--output`` gets the pass PNGs
    calibrate  measure this machine's constants (``--scale``) and save them
    report     the last analysis stored in the .blend (re-analyzed when missing or stale)
    export     one scene file per frame (``--frames 1-250 --output DIR``: DIR/frame_0001.npz, ...)
               for tracing without Blender (``core.load_mesh``, ``core.distributed``);
               a progress line per frame on stderr
    scan       sensor scans from ``--sensor NAME`` over ``--frames A-B`` into ``--output DIR``,
               one ``--format ply|las|npz|pcd|kitti`` file per frame (``operators/scan.py``)
    distance   each of ``--points FILE``'s points (.ply, .las, .npz, .npy) against the evaluated
               scene: its distance, nearest object and signed distance (negative inside, by
               the winding number); the JSON's summary, and with ``--output DIR``
               ``DIR/hybrid_raycast_distance.npz`` per point (``--max-distance D`` bounds it)

Options: ``--rays N`` (the expected rays: a custom budget), ``--json PATH`` (``-`` for
stdout), ``--output DIR`` (the plot PNG, the passes, and the JSON when ``--json`` is not
given), ``--blend PATH``, ``--scene NAME``, ``--selected-only``, ``--samples K``,
``--density D``, ``--candidates bvh,embree``, ``--workload camera|ao``, ``--object
NAME``, ``--ao-samples N``, ``--calibration PATH``, ``--scale tiny|quick|default``,
``--save [PATH]``, ``--frames 1-250`` (export, scan), ``--sensor NAME``,
``--format ply|las|npz|pcd|kitti``, ``--space world|sensor``, ``--motion frame|sweep``,
``--returns strongest|first|last|dual``, ``--beam-samples N``, ``--beam-divergence MRAD``
(scan: the last four override the sensor's settings for the run), ``--points FILE``,
``--max-distance D`` (distance).

``--json -`` puts the JSON, and nothing else, on stdout: while the command runs, file
descriptor 1 points at stderr, so every message (ours, Blender's own C-level prints such
as "Read blend" and "Info: Saved", Python prints) goes to stderr; the JSON is written to
the original stdout at the end.  For the camera passes the JSON's ``trace.passes`` holds
the depth image's ``near``/``far`` (``z = far - v * (far - near)``) and the object-ID
table (index, name, RGB colour in [0, 1]; the nearest table colour names a pixel).

The .blend is saved only with ``--save``: to the loaded file, or to PATH (a .blend).
Blender writes ``PATH@`` and renames it over PATH (checked with strace on bpy 5.0.1;
an existing file becomes ``PATH.blend1`` when the save-versions preference is on), so
a failed save never leaves a half-written file.  The AO bake and the results in
``scene.hybrid_raycast`` are kept; camera passes are generated images, so write them
with ``--output``.

Exit codes (one line on stderr says why):
    0  success
    1  internal error (a bug: the traceback is printed too)
    2  bad arguments (unknown option or command, --rays 0 or inf, a missing or non-.blend
       file before -c or in --blend, an unreadable --points file, ...)
    3  no geometry (nothing visible and render-enabled has triangles)
    4  unwritable path (--json, --output or the calibration file)
    5  invalid geometry (NaN or infinite vertex coordinates)
    6  nothing to trace (no active camera for the passes, no mesh for the AO bake)
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import os
import sys
import traceback
from pathlib import Path

import bpy
import numpy as np

from ..core import motion, pointcloud, sensors
from ..core.decide.measurements import SCALE_NOTES
from ..settings import RAYS_MAX
from . import calibrate as calibrate_mod
from .analyze import analysis_job, apply_analysis, results_json
from .calibrate import apply_calibration, calibration_job
from .jobs import BadInput, HRCError, Job, Unwritable, run_sync, writable_dir
from .trace import apply_trace, trace_job

COMMAND = "hybrid_raycast"
COMMANDS = ("analyze", "trace", "calibrate", "report", "export", "scan", "distance")
#: what ``distance --output DIR`` writes
DISTANCE_NPZ = "hybrid_raycast_distance.npz"
#: exit codes of the CLI itself; each failure's own code is its HRCError's ``code`` (operators/jobs.py)
EXIT_OK, EXIT_INTERNAL = 0, 1
PLOT_PNG = "hybrid_raycast_plot.png"
JSON_NAME = "hybrid_raycast_{command}.json"


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise BadInput(f"bad arguments: {message}")

    def exit(self, status=0, message=None):
        if message:
            print(message, file=sys.stderr)
        raise _Exit(status)


class _Exit(Exception):
    def __init__(self, status):
        self.status = status


def _positive(kind, most=None):
    def conv(text):
        try:
            number = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not math.isfinite(number):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
        value = kind(number)
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be greater than 0, got {text}")
        if most is not None and value > most:
            raise argparse.ArgumentTypeError(f"must be at most {most:g}, got {text}")
        return value
    return conv


def _sensor_number(name, kind):
    """An argparse type for the sensor setting ``name``: a ``kind`` (int: a whole number)
    within the property's own limits, read from ``HybridRaycastSensor``'s RNA."""
    def conv(text):
        from .scan import HybridRaycastSensor

        prop = HybridRaycastSensor.bl_rna.properties[name]
        try:
            value = int(text) if kind is int else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"not a {'whole number' if kind is int else 'number'}: {text!r}") from None
        if not (math.isfinite(value) and prop.hard_min <= value <= prop.hard_max):
            raise argparse.ArgumentTypeError(f"must be from {prop.hard_min:g} to {prop.hard_max:g}, got {text}")
        return value
    return conv


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog=f"blender -b scene.blend -c {COMMAND}",
                description="Grid or BVH for this scene and ray budget (Hybrid Ray Cast).",
                epilog="exit codes: 0 ok, 1 internal error, 2 bad arguments, 3 no geometry, "
                       "4 unwritable path, 5 invalid geometry, 6 nothing to trace")
    p.add_argument("command", choices=COMMANDS)
    p.add_argument("--rays", type=_positive(float, RAYS_MAX), help="expected rays (sets a custom ray budget)")
    p.add_argument("--json", help="write the JSON here ('-': stdout)")
    p.add_argument("--output", help="folder for the plot, the passes and (without --json) the JSON")
    p.add_argument("--blend", help="open this .blend first")
    p.add_argument("--scene", help="the scene to use (default: the file's active scene)")
    p.add_argument("--selected-only", action="store_true", help="only the selected objects")
    p.add_argument("--samples", type=_positive(int), help="sample rays timed through the grid (K)")
    p.add_argument("--density", type=_positive(float), help="grid cells per triangle")
    p.add_argument("--candidates", help="comma-separated: bvh, embree (default: the scene's setting)")
    p.add_argument("--workload", choices=("camera", "ao"), default="camera", help="trace: what to shoot")
    p.add_argument("--object", help="trace --workload ao: the mesh to bake (default: the active object)")
    p.add_argument("--ao-samples", type=_positive(int), help="trace --workload ao: rays per vertex")
    p.add_argument("--calibration", help="the calibration file to read and write")
    p.add_argument("--scale", choices=("tiny", "quick", "default"), default="default",
                   help=f"calibrate: how much to measure (default: {SCALE_NOTES['default']})")
    p.add_argument("--sensor", help="scan: the object to scan from (its hybrid_raycast_sensor settings)")
    p.add_argument("--format", choices=pointcloud.FORMATS, help="scan: file format (default: the sensor's)")
    p.add_argument("--space", choices=("world", "sensor"), help="scan: coordinates of the points (default: the sensor's)")
    p.add_argument("--motion", type=str.lower, choices=tuple(m.lower() for m in motion.MOTIONS),
                   help="scan: FRAME or SWEEP motion for this run (default: the sensor's)")
    p.add_argument("--returns", type=str.lower, choices=tuple(m.lower() for m in sensors.RETURN_MODES),
                   help="scan: which returns of a beam are reported, for this run (default: the sensor's)")
    p.add_argument("--beam-samples", type=_sensor_number("beam_samples", int), metavar="N",
                   help="scan: sub-rays per beam, 1-64, for this run (default: the sensor's)")
    p.add_argument("--beam-divergence", type=_sensor_number("beam_divergence", float), metavar="MRAD",
                   help="scan: full beam cone angle in milliradians, 0-100, for this run (default: the sensor's)")
    p.add_argument("--save", nargs="?", const="", metavar="PATH",
                   help="save the .blend afterwards (the AO bake, the results): to PATH, or the loaded file")
    p.add_argument("--frames", help="export: N, A-B or a list of them, e.g. 1-250; scan: A-B or N "
                   "(default: the scene's frame range)")
    p.add_argument("--points", help="distance: the points to measure (.ply, .las, .npz or .npy)")
    p.add_argument("--max-distance", type=_positive(float), help="distance: search no farther (default: no limit)")
    return p


def handler(argv) -> int:
    """What Blender calls with the arguments after ``-c hybrid_raycast``; the exit code.
    Blender exits right after, so with ``--json -`` its stdout stays on stderr."""
    return main(list(argv), blender_argv=list(sys.argv), keep_stdout_on_stderr=True)


#: Blender options that take values (the values are not files to open), with how many;
#: from ``blender --help`` of 4.3.2.  Only the arguments before ``-c`` are looked at.
_BLENDER_OPTION_VALUES = {
    **dict.fromkeys(("-f", "--render-frame", "-s", "--frame-start", "-e", "--frame-end", "-j", "--frame-jump",
                     "-o", "--render-output", "-E", "--engine", "-t", "--threads", "-F", "--render-format",
                     "-x", "--use-extension", "-S", "--scene", "-P", "--python", "--python-text",
                     "--python-expr", "--python-exit-code", "--addons", "--app-template", "--log",
                     "--log-level", "--log-file", "--debug-value", "--gpu-backend", "-setaudio",
                     "--cycles-device", "--verbose", "--gpu-compilation-subprocesses",
                     "--env-system-datafiles", "--env-system-scripts", "--env-system-extensions",
                     "--env-system-python"), 1),
    "-p": 4, "--window-geometry": 4,
}


def _files_before_command(blender_argv) -> list[str]:
    """The files Blender was asked to open: the arguments before ``-c``/``--command``
    that are neither options nor an option's values."""
    files, skip = [], 0
    for a in blender_argv[1:]:
        if a in ("-c", "--command"):
            break
        if skip:
            skip -= 1
        elif a.startswith("-"):
            skip = _BLENDER_OPTION_VALUES.get(a, 0)
        else:
            files.append(a)
    return files


def _check_opened_file(blender_argv):
    """A file given before ``-c`` that Blender did not open is a bad argument: Blender
    itself goes on with the startup scene (a missing path, a .txt, a truncated .blend)."""
    files = _files_before_command(blender_argv) if blender_argv else []
    if not files:
        return
    path = Path(files[-1])
    if not path.is_file():
        raise BadInput(f"bad arguments: {path}: no such file")
    loaded = bpy.data.filepath
    if not loaded or not Path(loaded).is_file() or not os.path.samefile(loaded, path):
        raise BadInput(f"bad arguments: {path}: not a .blend file Blender could open")


@contextlib.contextmanager
def _stdout_on_stderr(keep: bool):
    """Point file descriptor 1 at stderr while the command runs (Python's and Blender's
    C-level prints alike); yields a callable that writes text to the original stdout.
    With ``keep`` fd 1 stays on stderr afterwards and the original stdout is closed once
    written (Blender exits next); else both are restored."""
    original = os.dup(1)
    os.dup2(2, 1)  # what is still buffered (Python's or C's stdout) is flushed below, to stderr

    def flush_all():
        try:
            sys.stdout.flush()
        except (OSError, ValueError):
            pass
        with contextlib.suppress(Exception):  # C stdio buffers (Blender's printf)
            ctypes.CDLL(None).fflush(None)

    def write(text: str):
        flush_all()
        data = text.encode("utf-8")
        while data:
            data = data[os.write(original, data):]

    try:
        yield write
    finally:
        flush_all()
        if keep:
            os.close(original)
        else:
            os.dup2(original, 1)
            os.close(original)


def main(argv, stdout=None, stderr=None, *, blender_argv=None, keep_stdout_on_stderr=False) -> int:
    """Run one command; the exit code.  ``stdout``/``stderr`` default to the process's
    (then ``--json -`` works on file descriptors, see the module docstring);
    ``blender_argv`` is Blender's whole command line, to check the file given before -c."""
    real = stdout is None
    stdout = stdout or sys.stdout
    stderr = stderr or sys.stderr
    command = next((a for a in argv if a in COMMANDS), "")
    saved_path = calibrate_mod.CALIBRATION_PATH
    try:
        try:
            args = parser().parse_args(argv)
        except _Exit as e:  # --help
            return e.status
        if args.calibration:
            calibrate_mod.CALIBRATION_PATH = args.calibration
        _check_opened_file(blender_argv)
        if args.json != "-":
            return _run(args, stdout, stdout.write, stderr)
        if not real:
            return _run(args, stderr, stdout.write, stderr)
        with _stdout_on_stderr(keep_stdout_on_stderr) as write_json:
            return _run(args, sys.stdout, write_json, stderr)
    except HRCError as e:
        print(f"{' '.join(filter(None, (COMMAND, command)))}: error: {e}", file=stderr, flush=True)
        return e.code
    except Exception as e:
        traceback.print_exc()
        print(f"{' '.join(filter(None, (COMMAND, command)))}: error: internal error ({type(e).__name__}: {e})",
              file=stderr, flush=True)
        return EXIT_INTERNAL
    finally:
        calibrate_mod.CALIBRATION_PATH = saved_path


def _json_target(args) -> Path | None:
    if args.json == "-":
        return None
    if args.json:
        p = Path(args.json)
        if p.is_dir():
            raise Unwritable(f"unwritable path: --json {p} is a folder")
        writable_dir(p.parent if str(p.parent) else Path("."), "the folder of --json")
        if p.exists() and not os.access(p, os.W_OK):
            raise Unwritable(f"unwritable path: --json {p} is not writable")
        return p
    if args.output:
        return Path(args.output) / JSON_NAME.format(command=args.command)
    return None


def _scene(args):
    if args.blend:
        path = Path(args.blend)
        if not path.is_file():
            raise BadInput(f"bad arguments: --blend {path}: no such file")
        try:
            bpy.ops.wm.open_mainfile(filepath=str(path.resolve()))
        except RuntimeError as e:
            raise BadInput(f"bad arguments: --blend {path}: cannot open ({str(e).strip().splitlines()[-1]})") from None
    if args.scene:
        scene = bpy.data.scenes.get(args.scene)
        if scene is None:
            raise BadInput(f"bad arguments: --scene {args.scene!r}: no such scene "
                           f"(the file has {', '.join(repr(s.name) for s in bpy.data.scenes)})")
        return scene
    return bpy.context.scene


def _apply_settings(props, args):
    if args.rays is not None:
        props.expected_rays = args.rays
    if args.selected_only:
        props.selected_only = True
    if args.samples is not None:
        props.sample_rays = min(args.samples, 1 << 22)
    if args.density is not None:
        props.grid_density = args.density
    if args.candidates is not None:
        names = {c.strip().upper() for c in args.candidates.split(",") if c.strip()}
        unknown = names - {"BVH", "EMBREE"}
        if unknown:
            raise BadInput(f"bad arguments: --candidates: unknown {', '.join(sorted(unknown)).lower()} (use bvh, embree)")
        props.candidates = names
    if args.ao_samples is not None:
        props.ao_samples = min(args.ao_samples, 4096)


def _say(stdout, messages):
    for level, text in messages:
        print(f"{COMMAND}: {level.lower()}: {text}", file=stdout, flush=True)


def _view_layer(scene):
    ctx = bpy.context
    return ctx.view_layer if scene == ctx.scene else scene.view_layers[0]


def _analyze(scene, stdout):
    result = run_sync(analysis_job(scene, Job(), view_layer=_view_layer(scene)))
    _say(stdout, apply_analysis(scene, result))


def _write_plot(props, out_dir: Path) -> str:
    from ..core import plot
    from ..settings import figures_from_props

    f = figures_from_props(props)
    try:
        return plot.write_png(out_dir / PLOT_PNG, plot.plot_rgba(f, 640, 480))
    except OSError as e:
        raise Unwritable(f"unwritable path: {out_dir / PLOT_PNG}: {e.strerror or e}") from None


def _export(args, out_dir, stdout, stderr) -> dict:
    from .export import export_frames, parse_frames

    if out_dir is None:
        raise BadInput("bad arguments: export needs --output DIR (the folder for the scene files)")
    scene = _scene(args)
    frames = parse_frames(args.frames) if args.frames else list(range(scene.frame_start, scene.frame_end + 1))

    def progress(done, total, rec):
        print(f"{COMMAND} export: frame {rec['frame']} ({done}/{total}): {rec['triangles']:,} triangles -> {rec['path']}",
              file=stderr, flush=True)

    files = export_frames(scene, frames, out_dir, view_layer=_view_layer(scene), selected_only=args.selected_only,
                          progress=progress)
    print(f"{COMMAND} export: wrote {len(files)} scene files to {out_dir}", file=stdout, flush=True)
    return {"command": "export", "scene": scene.name, "output": str(out_dir), "files": files}


def _distance(args, out_dir, stdout) -> dict:
    """Each point's distance to the evaluated scene, its nearest object and its signed
    distance (negative inside, by the winding number): a scan checked against its model."""
    from ..core.pointcloud import PointFileError, read_points
    from . import query

    if not args.points:
        raise BadInput("bad arguments: distance needs --points FILE (.ply, .las, .npz or .npy)")
    try:
        pts = read_points(args.points)
    except PointFileError as e:
        raise BadInput(f"bad arguments: --points {e}") from None
    scene = _scene(args)
    depsgraph = _view_layer(scene).depsgraph
    md = args.max_distance if args.max_distance is not None else math.inf
    near = query.closest(pts, max_distance=md, depsgraph=depsgraph, selected_only=args.selected_only)
    inside = query.inside(pts, depsgraph=depsgraph, selected_only=args.selected_only)
    signed = np.where(inside, -near.distance, near.distance)
    found = near.found
    d = near.distance[found]
    stats = {"points": int(len(pts)), "found": int(found.sum()), "inside": int(inside.sum())}
    if d.size:
        stats.update({"median": float(np.median(d)), "p95": float(np.percentile(d, 95)), "max": float(d.max()),
                      "mean": float(d.mean())})
    ids, counts = np.unique(near.object_index[found], return_counts=True)
    per_object = {str(near.object_names[i]): int(c) for i, c in zip(ids, counts)}
    doc = {"command": "distance", "scene": scene.name, "file": str(args.points),
           "max_distance": md if math.isfinite(md) else None, "distance": stats, "nearest_objects": per_object,
           "structure": near.structure,
           "break_even": None if not math.isfinite(near.break_even) else float(near.break_even)}
    if out_dir is not None:
        from ..core.atomic import atomic_path

        target = out_dir / DISTANCE_NPZ
        try:
            with atomic_path(target) as tmp:
                with open(tmp, "wb") as fh:
                    np.savez(fh, points=pts, distance=near.distance, signed_distance=signed, inside=inside,
                             object_index=near.object_index, object_names=np.asarray(near.object_names, str),
                             closest=near.points, normals=near.normals)
        except OSError as e:
            raise Unwritable(f"unwritable path: {target}: {e.strerror or e}") from None
        doc["files"] = {"distance": str(target)}
    line = (f"{stats['found']:,} of {stats['points']:,} points within reach, {stats['inside']:,} inside"
            + (f"; distance median {stats['median']:.4g}, p95 {stats['p95']:.4g}, max {stats['max']:.4g}"
               if d.size else ""))
    print(f"{COMMAND} distance: {line}", file=stdout, flush=True)
    return doc


def _save_target(args) -> Path | None:
    """Where ``--save`` writes (checked before any work); None without ``--save``."""
    if args.save is None:
        return None
    target = args.save or bpy.data.filepath
    if not target:
        raise BadInput("bad arguments: --save: no .blend is loaded; give --save PATH")
    path = Path(target)
    if path.suffix.lower() != ".blend":
        raise BadInput(f"bad arguments: --save {path}: not a .blend path")
    if path.is_dir():
        raise Unwritable(f"unwritable path: --save {path} is a folder")
    writable_dir(path.parent if str(path.parent) else Path("."), "the folder of --save")
    if path.exists() and not os.access(path, os.W_OK):
        raise Unwritable(f"unwritable path: --save {path} is not writable")
    return path.resolve()


def _save(path: Path) -> str:
    # Blender writes "<path>@" and renames it over <path> (see the module docstring)
    try:
        bpy.ops.wm.save_as_mainfile(filepath=str(path), check_existing=False)
    except RuntimeError as e:
        raise Unwritable(f"unwritable path: --save {path}: {str(e).strip().splitlines()[-1]}") from None
    return str(path)


def _passes_json() -> dict:
    """How to read the camera pass images back: the depth range and the object-ID table."""
    from .passes import DEPTH, OBJECT_ID, object_id_colors

    depth, ids = bpy.data.images[DEPTH], bpy.data.images[OBJECT_ID]
    names = json.loads(ids.get("object_names", "[]"))
    colors = object_id_colors(len(names))
    return {
        "depth": {"near": float(depth.get("near", 0.0)), "far": float(depth.get("far", 0.0)),
                  "decode": "z = far - v * (far - near) where alpha > 0 (view-axis depth, scene units)"},
        # an 8-bit PNG holds each colour to within one step (Blender's own rounding): match the nearest
        "object_ids": [{"index": i, "name": n, "color": [round(float(c), 6) for c in colors[i]]}
                       for i, n in enumerate(names)],
    }


def _run(args, stdout, write_json, stderr=None) -> int:
    out_dir = writable_dir(Path(args.output), "--output") if args.output else None
    json_path = _json_target(args)
    if args.command == "calibrate":
        if args.save is not None:
            raise BadInput("bad arguments: --save: calibrate changes no scene")
        if args.blend:
            _scene(args)
        result = run_sync(calibration_job(Job(), scale=args.scale))
        _say(stdout, apply_calibration(None, result))
        cal = result["calibration"]
        doc = {"command": "calibrate", "path": str(result["path"]), "calibration": cal.to_dict()}
    elif args.command == "export":
        if args.save is not None:
            raise BadInput("bad arguments: --save: export changes no scene")
        doc = _export(args, out_dir, stdout, stderr or sys.stderr)
    elif args.command == "distance":
        if args.save is not None:
            raise BadInput("bad arguments: --save: distance changes no scene")
        doc = _distance(args, out_dir, stdout)
    elif args.command == "scan":
        from .scan import scan_command

        if args.save is not None:
            raise BadInput("bad arguments: --save: scan changes no scene (it returns to the current frame)")
        doc = scan_command(_scene(args), args, out_dir, stdout)
    else:
        scene = _scene(args)
        save_path = _save_target(args)
        props = scene.hybrid_raycast
        _apply_settings(props, args)
        if args.command == "analyze" or (args.command in ("report", "trace") and (not props.has_results or props.stale)):
            _analyze(scene, stdout)
        files = {}
        trace = None
        if args.command == "trace":
            result = run_sync(trace_job(scene, Job(), workload=args.workload, view_layer=_view_layer(scene),
                                        target=args.object))
            _say(stdout, apply_trace(scene, result))
            trace = {"workload": result["workload"], "structure": result["structure"],
                     "rays": len(result["rays"]["origins"]), "build_time": result["build_time"],
                     "trace_time": result["trace_time"], "rays_traced_after_plan": result["traced"],
                     "plan": result["plan"].to_dict()}
            if result["workload"] == "CAMERA":
                trace["passes"] = _passes_json()
            elif save_path is None:
                _say(stdout, [("INFO", "the AO bake is in this session only: pass --save [PATH] to keep it")])
            if result["workload"] == "CAMERA" and out_dir is not None:
                from .passes import DEPTH, NORMAL, OBJECT_ID, save_image

                for name, stem in ((DEPTH, "depth"), (NORMAL, "normal"), (OBJECT_ID, "object_id")):
                    try:
                        files[stem] = save_image(bpy.data.images[name], out_dir / f"hybrid_raycast_{stem}.png")
                    except (OSError, RuntimeError) as e:
                        raise Unwritable(f"unwritable path: cannot save {name} into {out_dir}: {e}") from None
        if out_dir is not None:
            files["plot"] = _write_plot(props, out_dir)
        doc = results_json(props)
        doc["command"] = args.command
        if trace is not None:
            doc["trace"] = trace
        if save_path is not None:
            files["blend"] = _save(save_path)
        if files:
            doc["files"] = files
        line = f"decision {props.decision}: {doc['summary_line']}"
        if trace is not None:
            line = (f"traced {trace['rays']:,} {trace['workload'].lower()} rays with {trace['structure'].upper()} "
                    f"in {trace['trace_time']:.2f} s; analysis {line}")
        print(f"{COMMAND} {args.command}: {line}", file=stdout, flush=True)
    text = json.dumps(doc, indent=2, default=str)
    if args.json == "-":
        write_json(text + "\n")
    elif json_path is not None:
        try:
            json_path.write_text(text, encoding="utf-8")
        except OSError as e:
            raise Unwritable(f"unwritable path: {json_path}: {e.strerror or e}") from None
        print(f"{COMMAND} {args.command}: wrote {json_path}", file=stdout, flush=True)
    return EXIT_OK
