"""The version matrix: the default test suite on each leg's bpy, then one table.

    make test-matrix                          (all legs of MATRIX_LEGS)
    python scripts/test_matrix.py [--demo] bpy-4.2 no-embree ...

Each leg is a venv made by ``make matrix-venv LEG=<leg>`` from requirements/<leg>.txt and
cached outside the clone.  The suite runs as ``make test`` runs it (``python -m pytest``
with the Makefile's PYTEST_ARGS); a leg that does not finish within --timeout is killed and
counts as failed.  Prints per leg: bpy, Python, numpy, embreex, passed/failed/skipped/errors,
and the seconds spent making (or finding) the venv, in the suite, and in the demo.  Exits
non-zero when any leg failed.
"""

import argparse
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COUNTS = ("passed", "failed", "skipped", "errors")
VERSIONS = (
    "import json, sys, importlib.metadata as m, importlib.util as u; "
    "v = lambda n: m.version(n) if u.find_spec(n) else '-'; "
    "print(json.dumps({'python': sys.version.split()[0], 'bpy': v('bpy'), 'numpy': v('numpy'), 'embreex': v('embreex')}))"
)


def run_streamed(cmd, timeout, log_path):
    """Run ``cmd`` in its own process group, echo and log its output; (exit code or None on timeout, text)."""
    lines = []
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)
        deadline = time.monotonic() + timeout
        try:
            for line in proc.stdout:
                sys.stdout.write(line)
                log.write(line)
                lines.append(line)
                if time.monotonic() > deadline:
                    raise subprocess.TimeoutExpired(cmd, timeout)
            return proc.wait(timeout=max(1.0, deadline - time.monotonic())), "".join(lines)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the group this call started
            proc.wait()
            return None, "".join(lines)


def summary_counts(text):
    """pytest's last summary line ('== 3 failed, 120 passed, 2 skipped in 95.1s ==' or '-q' style)."""
    found = None
    for line in text.splitlines():
        if re.search(r"\b(passed|failed|errors?|skipped|no tests ran)\b.* in [\d.]+s", line):
            found = line
    if found is None:
        return None
    counts = dict.fromkeys(COUNTS, 0)
    for n, word in re.findall(r"(\d+) (passed|failed|skipped|errors?)\b", found):
        counts["errors" if word.startswith("error") else word] = int(n)
    return counts


def run_leg(leg, args, outdir):
    row = {"leg": leg}
    t0 = time.perf_counter()
    made = subprocess.run(["make", "-s", "--no-print-directory", "matrix-venv", f"LEG={leg}"], cwd=ROOT,
                          stdout=subprocess.PIPE, text=True)
    row["venv_s"] = time.perf_counter() - t0
    if made.returncode != 0:
        row.update(ok=False, why=f"make matrix-venv LEG={leg} exited {made.returncode}")
        return row
    venv = Path(made.stdout.strip().splitlines()[-1])
    py = str(venv / "bin" / "python")
    row.update(json.loads(subprocess.run([py, "-c", VERSIONS], capture_output=True, text=True, check=True).stdout))
    print(f"\n== {leg}: bpy {row['bpy']}, Python {row['python']}, numpy {row['numpy']}, embreex {row['embreex']}"
          f" ({venv})", flush=True)
    t0 = time.perf_counter()
    code, text = run_streamed([py, "-m", "pytest", *shlex.split(args.pytest_args)], args.timeout, outdir / f"{leg}.log")
    row["suite_s"] = time.perf_counter() - t0
    row["exit"] = code
    counts = summary_counts(text)
    row.update(counts or dict.fromkeys(COUNTS, None))
    if code is None:
        row.update(ok=False, why=f"suite did not finish in {args.timeout:.0f} s (killed)")
    elif counts is None:
        row.update(ok=False, why=f"no pytest summary (exit code {code})")
    else:
        row["ok"] = code == 0 and counts["failed"] == 0 and counts["errors"] == 0
        row["why"] = "" if row["ok"] else f"exit code {code}"
    if args.demo:
        t0 = time.perf_counter()
        dcode, dtext = run_streamed([py, "scripts/demo.py", "--output", str(outdir / f"{leg}-demo")], args.timeout,
                                    outdir / f"{leg}-demo.log")
        row["demo_s"] = time.perf_counter() - t0
        decision = re.search(r"^\s*DECISION\s+(\S+)", dtext, re.M)
        row["demo"] = (decision.group(1) if decision else "?") if dcode == 0 else f"exit {dcode}"
        if dcode != 0:
            row["ok"] = False
            row["why"] = (row["why"] + "; " if row["why"] else "") + f"demo exit code {dcode}"
    return row


def table(rows, demo):
    head = ["leg", "bpy", "Python", "numpy", "embreex", "passed", "failed", "skipped", "errors",
            "venv s", "suite s"] + (["demo s", "demo"] if demo else []) + ["result"]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    fmt = lambda x: "-" if x is None else (f"{x:.0f}" if isinstance(x, float) else str(x))  # noqa: E731
    for r in rows:
        cells = [r["leg"], r.get("bpy"), r.get("python"), r.get("numpy"), r.get("embreex")]
        cells += [r.get(k) for k in COUNTS] + [r.get("venv_s"), r.get("suite_s")]
        cells += [r.get("demo_s"), r.get("demo")] if demo else []
        cells.append("ok" if r["ok"] else f"FAILED: {r['why']}")
        out.append("| " + " | ".join(fmt(c) for c in cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("legs", nargs="+", help="requirements/<leg>.txt names, e.g. bpy-4.2 no-embree")
    ap.add_argument("--pytest-args", default="-q -ra", help="pytest's arguments (make passes PYTEST_ARGS)")
    ap.add_argument("--demo", action="store_true", help="also run the demo (scripts/demo.py) on each leg")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds before a leg's suite counts as hung")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "matrix", help="logs and the table (matrix.md)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = [run_leg(leg, args, args.out) for leg in args.legs]
    text = table(rows, args.demo)
    (args.out / "matrix.md").write_text(text + "\n")
    print("\n== version matrix (machine: %d cores, load %s)\n%s" % (os.cpu_count(), open("/proc/loadavg").read().split()[0]
                                                                      if os.path.exists("/proc/loadavg") else "?", text))
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
