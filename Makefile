# Hybrid Ray Cast: the two commands a new machine needs are `make demo` and `make test`.
# Both create the project virtual environment (.venv, pinned in requirements-dev.txt) when missing.

PYTHON ?= python3.11
VENV   := .venv
O3D_VENV := .venv-open3d
PY     := $(VENV)/bin/python
BPYDIR  = $(shell $(PY) -c "import importlib.util as u, os; print(os.path.dirname(u.find_spec('bpy').origin))" 2>/dev/null)
# bpy keeps Blender's scripts in a folder named after its version (bpy/5.0/scripts, bpy/4.2/...).
BPYVER  = $(notdir $(patsubst %/,%,$(dir $(firstword $(wildcard $(BPYDIR)/[0-9]*.[0-9]*/scripts)))))
BLENDER_EXT = $(BPYDIR)/$(BPYVER)/scripts/addons_core/bl_pkg/cli/blender_ext.py
VALID_TAGS  = $(BPYDIR)/$(BPYVER)/scripts/modules/_bpy_internal/extensions/tags.py
WHEELS := $(shell sed -n 's|^ *"\./\(wheels/[^"]*\.whl\)",*|\1|p' blender_manifest.toml)
VERSION := $(shell sed -n 's/^version = "\(.*\)"/\1/p' blender_manifest.toml)
PLATFORMS := $(shell sed -n 's/^platforms = \[\(.*\)\]/\1/p' blender_manifest.toml | tr -d '",' | tr '-' '_')
# One zip per platform of the manifest, named as blender_ext.py --split-platforms names them.
ZIPS   := $(foreach p,$(PLATFORMS),dist/hybrid_raycast-$(VERSION)-$(p).zip)
# This machine's package (the real-Blender suite installs it).
ZIP    := dist/hybrid_raycast-$(VERSION)-linux_x64.zip

.PHONY: demo test test-slow test-matrix matrix-venv real-blender venv open3d-venv wheels validate extension bench-extract bench-trace bench-threads bench-distributed bench-scan bench-frames bench-proximity bench-point-decision report report-halves docs clean

## The main job: analyze and trace the built-in demo scene headless; prints the decision, writes out/demo/ (JSON, passes, plot).
demo: $(VENV)/.stamp
	$(PY) scripts/demo.py --output out/demo

## The tests (the README's test command; a few minutes on 2 cores): everything but the tests marked slow.
PYTEST_ARGS := -q -ra -m 'not slow'
test: $(VENV)/.stamp wheels
	$(PY) -m pytest $(PYTEST_ARGS)

## The slow tests, CI's leg of their own: real calibrations, the report's end-to-end run, the zip
## install round trips, pip install in a fresh venv.
test-slow: $(VENV)/.stamp wheels
	$(PY) -m pytest -q -ra -m slow

## The API reference: pdoc (pinned in requirements-dev.txt) over the docstrings of api, core (every
## submodule), operators.query and operators.scan; writes out/docs/api/index.html. Fails when pdoc cannot import a module.
docs: $(VENV)/.stamp
	rm -rf out/docs/api
	$(PY) scripts/make_docs.py --output out/docs/api

## The version matrix: the same suite on each leg's bpy, in its own venv made from
## requirements/<leg>.txt (its '# python: X.Y' line names the interpreter); prints a table.
## The venvs are cached outside the clone, named by a hash of their requirement files, so a
## fresh clone reuses them and a changed pin makes a new one.
MATRIX_LEGS  ?= bpy-4.2 bpy-4.5 bpy-5.3 no-embree
MATRIX_CACHE ?= /var/cache/hybrid_raycast/venvs
MATRIX_ARGS  ?=
leg_venv = $(MATRIX_CACHE)/$(1)-$(shell cat requirements/$(1).txt requirements/test.txt | sha256sum | cut -c1-12)
test-matrix: $(VENV)/.stamp wheels
	$(PY) scripts/test_matrix.py --pytest-args="$(PYTEST_ARGS)" $(MATRIX_ARGS) $(MATRIX_LEGS)

## One leg's venv (make matrix-venv LEG=bpy-4.2); prints its path.
matrix-venv:
	@test -f "requirements/$(LEG).txt" || { echo "matrix-venv: LEG must be one of: $(MATRIX_LEGS)" >&2; exit 2; }
	@$(MAKE) -s $(call leg_venv,$(LEG))/.stamp LEG=$(LEG) >&2
	@echo $(call leg_venv,$(LEG))
# No prerequisites: the hash in the folder's name stands for the requirement files (a fresh
# clone's files are always newer than the cache). Built beside, then moved, so a half-made venv
# is never taken for a finished one.
$(MATRIX_CACHE)/%/.stamp:
	@py=; v=$$(sed -n 's/^# python: *//p' requirements/$(LEG).txt); \
	for c in python$$v $$(pyenv root 2>/dev/null)/versions/$$v*/bin/python$$v; do \
	  "$$c" -c '' 2>/dev/null && { py=$$c; break; }; done; \
	test -n "$$py" || { echo "matrix-venv: no working python$$v for $(LEG)" >&2; exit 1; }; \
	echo "== making $(@D) with $$py"; \
	rm -rf $(@D).tmp && mkdir -p $(MATRIX_CACHE) && "$$py" -m venv $(@D).tmp && \
	$(@D).tmp/bin/python -m pip install -q -r requirements/$(LEG).txt && \
	touch $(@D).tmp/.stamp && rm -rf $(@D) && mv $(@D).tmp $(@D)

## The real-Blender suite: Blender 4.3.2 (Debian trixie rootfs), CLI and GUI; needs root, skips otherwise.
real-blender: $(ZIPS)
	tests/real_blender/run.sh $(ZIP) out/real_blender

venv: $(VENV)/.stamp
$(VENV)/.stamp: requirements-dev.txt requirements/test.txt
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

## The installable zips, one per platform, built by Blender's own tool (no tests inside).
extension: $(ZIPS)
	@ls -l $(ZIPS)
$(ZIPS) &: $(VENV)/.stamp wheels $(shell git ls-files '*.py' '*.toml' 2>/dev/null)
	@mkdir -p dist
	$(PY) $(BLENDER_EXT) build --split-platforms --valid-tags $(VALID_TAGS) --source-dir . --output-dir dist

bench-extract: $(VENV)/.stamp
	$(PY) scripts/bench_extract.py

## The engine table: raw embreex, core's Embree (defaults and 1 thread), numpy BVH and grid, Blender's
## BVHTree loop and Open3D on 3 icospheres and a 1M Suzanne, 1M random and camera rays (a few minutes;
## run it as `flock /tmp/hrc-bench.lock make bench-trace`).  BENCH_ARGS=--scenes icospheres, --repeats N ...
## The older per-size table against all of Blender's peers: .venv/bin/python scripts/bench_trace.py --help
bench-trace: $(VENV)/.stamp $(O3D_VENV)/.stamp
	$(PY) scripts/bench_trace.py --engines $(BENCH_ARGS)

## 1 -> 2 threads of the numpy BVH and grid on the engine scenes, 1M rays, in adjacent pairs (about 6
## minutes; run it as `flock /tmp/hrc-bench.lock make bench-threads`).  BENCH_ARGS=--kinds bvh,grid,embree ...
bench-threads: $(VENV)/.stamp
	$(PY) scripts/bench_threads.py $(BENCH_ARGS)

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

## Frames at the speed of the trace: per-frame api.scan / api.cast on scenes kept across frames (a static scene with a
## moving sensor, rigid and deforming motion, a camera flythrough, casts from a moving point, a cast after frame_set)
## vs a scene.ray_cast loop over the same rays (timing lock held).  BENCH_ARGS=--memory, --scenario NAME, --small ...
bench-frames: $(VENV)/.stamp
	flock /tmp/hrc-bench.lock $(PY) scripts/bench_frames.py $(BENCH_ARGS)

## Closest-point queries: the numpy tree against Blender's BVHTree.find_nearest loop and Open3D on flat grids of
## 20k and 1M triangles, and the winding number's tree against its exact sum (timing lock held).
bench-proximity: $(VENV)/.stamp
	flock /tmp/hrc-bench.lock $(PY) scripts/bench_proximity.py $(BENCH_ARGS)

## The decision for point queries (closest point: grid or BVH) against measured break-evens on the
## evaluation set's halves, with the shipped constants (timing lock held; about a minute a half).
bench-point-decision: $(VENV)/.stamp
	flock /tmp/hrc-bench.lock $(PY) scripts/point_decision.py --model-from-calibration --scenes ../shared/eval/tuning --scenes ../shared/eval/final $(BENCH_ARGS)

## The decision's goals on the evaluation set's two halves side by side: the final half with a
## calibration made in its truths' passes, the tuning half with it reused (about 18 minutes; timing
## lock held); BENCH_ARGS=--tables-only prints the table of the last run.
report-halves: $(VENV)/.stamp
	flock /tmp/hrc-bench.lock $(PY) scripts/report_halves.py $(BENCH_ARGS)

## The paper's evaluation: calibrate on procedural scenes, estimate and measure on ../shared/scenes,
## the calibration and the truths in the same passes (about 42 minutes on the 2-core VM, 13 with
## REPORT_ARGS="--reuse-calibration --calibration core/default_calibration.json"; --quick: a smoke run).
report: $(VENV)/.stamp
	$(PY) scripts/report.py $(REPORT_ARGS)

clean:
	rm -rf dist out .pytest_cache
