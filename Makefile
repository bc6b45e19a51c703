# Hybrid Ray Cast: the two commands a new machine needs are `make demo` and `make test`.
# Both create the project virtual environment (.venv, pinned in requirements-dev.txt) when missing.

PYTHON ?= python3.11
VENV   := .venv
O3D_VENV := .venv-open3d
PY     := $(VENV)/bin/python
BPYDIR  = $(shell $(PY) -c "import importlib.util as u, os; print(os.path.dirname(u.find_spec('bpy').origin))" 2>/dev/null)
BLENDER_EXT = $(BPYDIR)/5.0/scripts/addons_core/bl_pkg/cli/blender_ext.py
VALID_TAGS  = $(BPYDIR)/5.0/scripts/modules/_bpy_internal/extensions/tags.py
WHEELS := $(shell sed -n 's|^ *"\./\(wheels/[^"]*\.whl\)",*|\1|p' blender_manifest.toml)
VERSION := $(shell sed -n 's/^version = "\(.*\)"/\1/p' blender_manifest.toml)
ZIP    := dist/hybrid_raycast-$(VERSION).zip

.PHONY: demo test test-fast real-blender venv open3d-venv wheels validate extension bench-extract bench-trace bench-distributed bench-scan report clean

## The main job: analyze and trace the built-in demo scene headless; prints the decision, writes out/demo/ (JSON, passes, plot).
demo: $(VENV)/.stamp
	$(PY) scripts/demo.py --output out/demo

## The tests (what CI runs).
test: $(VENV)/.stamp wheels
	$(PY) -m pytest -q -ra

## The real-Blender suite: Blender 4.3.2 (Debian trixie rootfs), CLI and GUI; needs root, skips otherwise.
real-blender: $(ZIP)
	tests/real_blender/run.sh $(ZIP) out/real_blender

## The tests without the slower Blender install round-trip.
test-fast: $(VENV)/.stamp
	$(PY) -m pytest -q -ra -m "not slow"

venv: $(VENV)/.stamp
$(VENV)/.stamp: requirements-dev.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements-dev.txt
	touch $@

## embreex wheels named in the manifest, fetched from PyPI (never committed).
wheels: $(WHEELS)
wheels/%.whl: | $(VENV)/.stamp
	@mkdir -p wheels
	$(PY) scripts/fetch_wheels.py $@

## Blender's own validator, with Blender's own tags.
validate: $(VENV)/.stamp wheels
	$(PY) $(BLENDER_EXT) validate --valid-tags $(VALID_TAGS) .

## The installable zip, built by Blender's own tool (no tests inside).
extension: $(ZIP)
$(ZIP): $(VENV)/.stamp wheels $(shell git ls-files '*.py' '*.toml' 2>/dev/null)
	@mkdir -p dist
	$(PY) $(BLENDER_EXT) build --valid-tags $(VALID_TAGS) --source-dir . --output-filepath $@

bench-extract: $(VENV)/.stamp
	$(PY) scripts/bench_extract.py

## The engine table: raw embreex, core's Embree (defaults and 1 thread), numpy BVH and grid, Blender's
## BVHTree loop and Open3D on 3 icospheres and a 1M Suzanne, 1M random and camera rays (a few minutes;
## run it as `flock /tmp/hrc-bench.lock make bench-trace`).  BENCH_ARGS=--scenes icospheres, --repeats N ...
## The older per-size table against all of Blender's peers: .venv/bin/python scripts/bench_trace.py --help
bench-trace: $(VENV)/.stamp $(O3D_VENV)/.stamp
	$(PY) scripts/bench_trace.py --engines $(BENCH_ARGS)

## Open3D 0.20 for the benchmark only, in its own venv: it needs numpy 2, which bpy 5.0.1 excludes.
## Its import needs Debian's libusb-1.0-0 (apt-get install -y libusb-1.0-0).
open3d-venv: $(O3D_VENV)/.stamp
$(O3D_VENV)/.stamp: requirements-open3d.txt
	test -x $(O3D_VENV)/bin/python || $(PYTHON) -m venv $(O3D_VENV)
	$(O3D_VENV)/bin/python -m pip install -q --upgrade pip
	$(O3D_VENV)/bin/python -m pip install -q -r requirements-open3d.txt
	touch $@

## core.distributed: 1 vs 2 Dask workers (LocalCluster) against a local trace, 10M rays, ~1.1M triangles.
bench-distributed: $(VENV)/.stamp
	$(PY) scripts/bench_distributed.py $(BENCH_ARGS)

## Sensor scans: 64 x 2,048 rays per frame over 100 frames of an animated scene vs a scene.ray_cast loop (timing lock held).
bench-scan: $(VENV)/.stamp
	flock /tmp/hrc-bench.lock $(PY) scripts/bench_scan.py

## The paper's evaluation: calibrate on procedural scenes, estimate and measure on ../shared/scenes
## (about 8 minutes; REPORT_ARGS=--quick for a 5-second smoke run).
report: $(VENV)/.stamp
	$(PY) scripts/report.py $(REPORT_ARGS)

clean:
	rm -rf dist out .pytest_cache
