"""The headless CLI in a real Blender: `blender -b FILE.blend -c hybrid_raycast ...`.

Run with plain python3 inside the rootfs after checks.py saved the .blend files:
    python3 check_cli.py WORK
The extension is enabled in the user preferences (installed with `-e`), which is what
registers the command.  Checks the exit codes (0, and 2-6 for each failure, with one
line from the add-on on stderr; a missing or non-.blend file before -c and --rays inf
exit 2), the JSON of every command, that ``--json -`` leaves nothing but the JSON on
stdout, that ``trace --workload ao --save`` writes the bake into the loaded file, and that
``export`` writes a scene file per frame that numpy reads without pickle.  Writes
real_blender_cli.json; exits 1 on the first failure.
"""

import json
import subprocess
import sys
from pathlib import Path

WORK = Path(sys.argv[1])
OUT = WORK / "cli_out"
results = {}


def check(name, ok, detail=""):
    results[name] = bool(ok)
    print(f"{'ok  ' if ok else 'FAIL'} {name} {detail}", flush=True)
    if not ok:
        (WORK / "real_blender_cli.json").write_text(json.dumps(results, indent=2))
        sys.exit(1)


def blender(blend, *args):
    cmd = ["blender", "-b"] + ([str(WORK / blend)] if blend else []) + ["-c", "hybrid_raycast", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    ours = [x for x in p.stderr.splitlines() if x.startswith("hybrid_raycast")]
    return p.returncode, p.stdout, ours, p


code, out, err, p = blender("demo.blend", "analyze", "--json", str(WORK / "analyze.json"), "--output", str(OUT))
check("analyze exits 0", code == 0, f"rc={code} {err} {p.stderr[-500:]}")
doc = json.loads((WORK / "analyze.json").read_text())
check("analyze JSON has a decision", doc["decision"] in {"GRID", "BVH", "EMBREE"}, doc["decision"])
be = doc["break_even"]
rays = doc["expected_rays"]
check("the decision follows the break-even",
      (doc["decision"] == "GRID") == (be["rays"] is None or rays <= be["rays"] * (1 + 1e-6)),
      f"{doc['decision']} R={rays:.0f} R*={be['rays']}")
check("analyze JSON: every panel figure",
      all(k in doc for k in ("summary", "budget", "structures", "calibration", "analyzed_at", "stale", "certain"))
      and doc["summary"]["triangles"] > 10000 and doc["budget"]["source"] == "RENDER"
      and doc["budget"]["width"] == 640 and doc["structures"]["grid"]["per_ray"] > 0,
      f"{doc['summary']['triangles']} triangles")
check("analyze used the calibration made by checks.py", doc["calibration"]["source"] == "measured", doc["calibration"]["message"])
check("analyze wrote the plot", (OUT / "hybrid_raycast_plot.png").is_file())
print("   ", doc["summary_line"])

code, out, err, p = blender("demo.blend", "trace", "--rays", "1e7", "--output", str(OUT))
check("trace exits 0", code == 0, f"rc={code} {err} {p.stderr[-500:]}")
tdoc = json.loads((OUT / "hybrid_raycast_trace.json").read_text())
check("trace JSON: 640x360 camera rays", tdoc["trace"]["rays"] == 640 * 360 and tdoc["trace"]["workload"] == "CAMERA",
      f"{tdoc['trace']['rays']} {tdoc['trace']['workload']} rays with {tdoc['trace']['structure']}")
check("trace wrote the passes", all((OUT / f"hybrid_raycast_{s}.png").stat().st_size > 1000
                                    for s in ("depth", "normal", "object_id")))
check("--rays sets the budget", tdoc["expected_rays"] == 1e7 and tdoc["budget"]["source"] == "CUSTOM")

code, out, err, p = blender("demo.blend", "report", "--json", "-")
check("report exits 0", code == 0, f"rc={code} {err}")
try:
    rdoc = json.loads(out)  # the whole stdout: Blender's own prints and our messages are on stderr
except ValueError:
    rdoc = {}
check("report --json -: stdout is the JSON alone", rdoc.get("decision") in {"GRID", "BVH", "EMBREE"} and "break_even" in rdoc,
      repr(out[:300]))
check("report --json -: the messages went to stderr", any("decision" in x for x in err), f"{err}")

code, out, err, p = blender("demo.blend", "trace", "--json", "-")
try:
    tdoc = json.loads(out)
except ValueError:
    tdoc = {}
passes = tdoc.get("trace", {}).get("passes", {})
check("trace --json -: stdout is the JSON alone, with the depth range and the object-ID table",
      code == 0 and 0 < passes.get("depth", {}).get("near", 0) < passes.get("depth", {}).get("far", 0)
      and "Suzanne" in {e["name"] for e in passes.get("object_ids", [])},
      f"rc={code} {err} {out[:300]!r}")

# --save with no PATH writes the loaded file (Blender writes FILE@, then renames it over FILE)
(WORK / "ao.blend").write_bytes((WORK / "nocamera.blend").read_bytes())
code, out, err, p = blender("ao.blend", "trace", "--workload", "ao", "--object", "Cube", "--ao-samples", "4", "--save",
                            "--json", "-")
check("trace --workload ao --save exits 0 and says so in the JSON",
      code == 0 and json.loads(out)["files"]["blend"] == str(WORK / "ao.blend"), f"rc={code} {err} {out[:300]!r}")
probe = WORK / "ao_probe.txt"
subprocess.run(["blender", "-b", str(WORK / "ao.blend"), "--python-expr",
                f"import bpy, pathlib; pathlib.Path({str(probe)!r}).write_text("
                "str('HRC AO' in bpy.data.objects['Cube'].data.color_attributes))"],
               capture_output=True, text=True, timeout=300)
check("the saved .blend holds the AO bake", probe.is_file() and probe.read_text() == "True",
      probe.read_text() if probe.is_file() else "no probe output")
check("no temporary save file is left", not (WORK / "ao.blend@").exists())

code, out, err, p = blender("demo.blend", "export", "--frames", "1-2", "--output", str(WORK / "scenes"))
check("export exits 0 with a progress line per frame on stderr",
      code == 0 and sum(x.startswith("hybrid_raycast export: frame ") for x in err) == 2, f"rc={code} {err}")
import numpy as np  # noqa: E402  (Debian's numpy 2.x: the scene file is plain .npz, read without pickle)

for frame in (1, 2):
    # version 2 (instanced): each mesh once, end to end, and per instance its mesh; the scene's
    # triangles are every instance's mesh's
    with np.load(WORK / "scenes" / f"frame_{frame:04d}.npz", allow_pickle=False) as z:
        per_mesh = np.diff(z["mesh_triangle_start"].astype(np.int64))  # (K + 1,) offsets
        placed = int(per_mesh[z["instance_mesh"]].sum())
        check(f"export frame {frame}: a scene file with the analyzed triangles, each mesh once",
              str(z["format"]) == "hybrid_raycast.scene" and int(z["version"]) == 2 and int(z["frame"]) == frame
              and z["mesh_vertices"].dtype == np.float32 and placed == doc["summary"]["triangles"]
              and len(z["instance_matrix"]) == len(z["instance_mesh"])
              and len(z["mesh_triangles"]) <= placed, f"{placed} triangles placed")

code, out, err, p = blender(None, "calibrate", "--scale", "tiny", "--calibration", str(WORK / "cli_cal.json"))
check("calibrate exits 0 and writes the file", code == 0 and (WORK / "cli_cal.json").is_file(), f"rc={code} {err}")

# sensor scans (issue 13): the text object lying on the ground as a rotating LiDAR (the default
# VLP-16 settings): its upper lasers see Suzanne and the ring of instances; LAS files
scan_dir = WORK / "cli_out" / "scan"
code, out, err, p = blender("demo.blend", "scan", "--sensor", "Title", "--frames", "1-2", "--output", str(scan_dir),
                            "--format", "las")
check("scan exits 0", code == 0, f"rc={code} {err} {p.stderr[-500:]}")
las = sorted(scan_dir.glob("Title_*.las"))
points = [int.from_bytes(f.read_bytes()[247:255], "little") for f in las]  # LAS 1.4 header: number of point records
check("scan wrote one LAS 1.4 file per frame with points", [f.name for f in las] == ["Title_00001.las", "Title_00002.las"]
      and all(f.read_bytes()[:4] == b"LASF" for f in las) and all(n > 500 for n in points), f"{las} {points}")

(WORK / "notes.txt").write_text("not a .blend file\n")
for name, blend, args, want, words in (
    ("scan outside the frame range", "demo.blend", ["scan", "--sensor", "Title", "--frames", "1-999999",
                                                    "--output", str(scan_dir)], 2, "outside the scene's frame range"),
    ("bad arguments", "demo.blend", ["analyze", "--rays", "0"], 2, "greater than 0"),
    ("infinite rays", "demo.blend", ["analyze", "--rays", "inf"], 2, "finite"),
    ("a missing file", "missing.blend", ["analyze"], 2, "no such file"),
    ("a non-.blend file", "notes.txt", ["analyze"], 2, "not a .blend file"),
    ("unknown command", "demo.blend", ["frobnicate"], 2, "invalid choice"),
    ("no geometry", "empty.blend", ["analyze"], 3, "no geometry"),
    ("unwritable path", "demo.blend", ["analyze", "--json", "/proc/hrc/x.json"], 4, "unwritable path"),
    ("invalid geometry", "nan.blend", ["analyze"], 5, "NaN or infinite"),
    ("nothing to trace", "nocamera.blend", ["trace"], 6, "no camera"),
):
    code, out, err, p = blender(blend, *args)
    check(f"{name}: exit {want} with one line", code == want and len(err) == 1 and words in err[0],
          f"rc={code} {err}")

(WORK / "real_blender_cli.json").write_text(json.dumps(results, indent=2))
print(f"CLI: {len(results)} passed, 0 failed")
