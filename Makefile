# surfelslam: every target creates .venv when it is missing, so each works alone on a fresh clone.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
VIZ_STAMP := $(VENV)/.viz-installed
DEMO_OUT ?= out/demo

.PHONY: demo test test-all test-fast fuzz warmup bench lint docs clean wheel-check

$(PY):
	$(PYTHON) -m venv $(VENV)

# --no-compile: modules are byte-compiled when first imported, not every file of every dependency up front. That needs
# Python to keep the bytecode it compiles: an inherited PYTHONDONTWRITEBYTECODE would make every process (each test
# worker, warm-up and command a test runs) compile every module it imports again, seconds each. Commands started
# outside make with it set are covered by `make warmup`: once the kernels are compiled, surfelslam.tools.bytecode
# writes the bytecode of every module a `surfelslam run` imports where it is missing (about 270 in a venv uv
# installed: a second of CPU at every command's start otherwise).
unexport PYTHONDONTWRITEBYTECODE
COMMA := ,
PIP_INSTALL := $(PY) -m pip install --quiet --no-compile
# uv (a PyPI package, put into the venv by pip) downloads and unpacks in parallel: the same packages in about 13 s
# where pip takes about 60 s on a fresh machine. Where uv cannot be had or fails, pip installs instead.
# $(call INSTALL,extras): the project, editable, with those extras.
INSTALL = ($(PIP_INSTALL) uv && $(VENV)/bin/uv pip install --quiet --python $(PY) -e ".[$(1)]") || \
	$(PIP_INSTALL) -e ".[$(1)]"

$(STAMP): $(PY) pyproject.toml
	$(call INSTALL,dev)
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m surfelslam.tools.demo $(DEMO_OUT)

# the tests also cover `surfelslam rerun` and the live viewer, which need the optional rerun-sdk (the `viz` extra),
# and `surfelslam batch` on Ray (the `batch` extra: ray without the dashboard, about 5 s more of a cold install):
# one install of the extras (one dependency resolution), the dev extra alone if one of them cannot be had
$(VIZ_STAMP): $(PY) pyproject.toml
	$(call INSTALL,dev$(COMMA)viz$(COMMA)batch) || (echo "rerun-sdk or ray not installable here: their tests skip" && \
	$(call INSTALL,dev))
	touch $(VIZ_STAMP) $(STAMP)

# The suite runs on every core (pytest-xdist). The numba kernels are compiled first, once, by three warm-up processes
# side by side (surfelslam.warmup parts; three on two cores, so that the OS evens out their unequal lengths), so the
# workers load them from numba's on-disk cache
# instead of each compiling the same kernels; a kernel a worker still compiles is written to a temporary name and
# renamed by numba, so workers never read a torn cache file. Tests are handed out one at a time to whichever worker is
# free (--dist loadgroup): first the groups that share a module fixture or a cached run (marked xdist_group, so the
# shared work is done once, on one worker), then the whole-sequence tests (marked slow, tests/conftest.py), then the rest.
PYTEST_WORKERS ?= auto
PYTEST_DIST := --dist loadgroup
test: $(VIZ_STAMP) warmup
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) $(PYTEST_DIST) -m "not heavy"

# Everything, with the tests that run several long tracker configurations each or a local Ray cluster (marked `heavy`).
test-all: $(VIZ_STAMP) warmup
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) $(PYTEST_DIST)

warmup: $(STAMP)
	@$(PY) -m surfelslam.warmup dense & dense=$$!; $(PY) -m surfelslam.warmup outputs & outputs=$$!; \
	$(PY) -m surfelslam.warmup sparse shape; sparse=$$?; wait $$dense; d=$$?; wait $$outputs; o=$$?; \
	[ $$(( d || o || sparse )) = 0 ] && $(PY) -m surfelslam.tools.bytecode

# The edit loop: unit tests and kernels, no whole-sequence runs (tests marked `slow` are left out).
test-fast: $(STAMP)
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) $(PYTEST_DIST) -m "not slow and not shared"

# Property-based fuzzing of every reader and loader (tests/fuzz, hypothesis) with the large budget of the `fuzz`
# profile (tests/fuzz/conftest.py): random mutated inputs, a few minutes on two cores. `make test` runs the same tests
# with the small, derandomized `fast` profile. The examples come from FUZZ_SEED, so a run is reproducible and a find can
# be replayed; another seed (make fuzz FUZZ_SEED=7) explores other inputs.
FUZZ_SEED ?= 0
fuzz: $(STAMP)
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) tests/fuzz --hypothesis-profile=fuzz --hypothesis-seed=$(FUZZ_SEED)

bench: $(STAMP)
	@dpkg -s libusb-1.0-0 >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) || true
	$(call INSTALL,dev$(COMMA)bench$(COMMA)viz) || { \
	$(call INSTALL,dev$(COMMA)bench) || echo "open3d not installable here: benchmarks run without the side-by-side"; \
	$(call INSTALL,dev$(COMMA)viz) || echo "rerun-sdk not installable here: the bench runs without the viewer section"; }
	$(PY) -m benchmarks.run_all $(BENCH_ARGS)

# the configuration reference, generated from the settings' metadata (a test checks the committed page is current)
docs: $(STAMP)
	$(PY) -m surfelslam.tools.gen_docs docs/config_reference.md

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks

clean:
	rm -rf $(VENV) out build *.egg-info src/*.egg-info

# The package as a user installs it: a wheel in a fresh venv, away from the source tree, runs `surfelslam run ...
# --config fast` (presets are package data) and `surfelslam mesh` on a tiny synthetic sequence (.ci/wheel_check).
wheel-check: $(STAMP)
	PYTHON=$(PYTHON) UV=$(VENV)/bin/uv .ci/wheel_check
