# Two entry points that work on a fresh machine (Debian, Python 3.11, pip, no GPU):
#   make demo   sets up .venv when missing, then runs the whole pipeline on the built-in demo capture
#   make test   sets up .venv when missing, then runs the test suite on 2 pytest-xdist workers
#               (what CI runs: .ci/run; `make test PYTEST_WORKERS=0` runs it in one process)
PYTHON ?= python3
VENV   ?= .venv
# On CPU machines torch must be exactly this (a local CPU wheel exists; a looser spec pulls CUDA builds).
TORCH  ?= torch==2.13.0
BIN    := $(VENV)/bin
# Test workers (pytest-xdist): CI has 2 cores, and every test keeps to one torch thread
# (tests/conftest.py). A worker takes whole files (a module's fixtures are made once), in the
# order tests/conftest.py gives them: the files with slow tests first.
PYTEST_WORKERS ?= 2
PYTEST_XDIST   := -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder
STAMP  := $(VENV)/.volcap-installed

.PHONY: setup demo test test-quick bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH)"
	$(BIN)/python -m pip install -q -e ".[test]"
	@touch $@

demo: $(STAMP)
	$(BIN)/volcap demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -ra --durations=15 $(PYTEST_XDIST)

# The quick subset: everything but the slow end-to-end tests.
test-quick: $(STAMP)
	$(BIN)/python -m pytest -q -ra $(PYTEST_XDIST) -m "not slow"

# Every benchmark under bench/, one after the other (about an hour on 2 cores; figures and the
# command of each in docs/benchmarks.md). Run one alone with `.venv/bin/python bench/NAME.py`.
bench: $(STAMP)
	$(BIN)/python -m pip install -q -e ".[bench]"
	$(BIN)/python bench/bench_store.py
	$(BIN)/python bench/bench_ingest.py
	$(BIN)/python bench/bench_rasterizer.py
	$(BIN)/python bench/bench_calibration.py
	$(BIN)/python bench/bench_static_resolution.py
	$(BIN)/python bench/bench_poly4dgs.py
	$(BIN)/python bench/bench_production.py
	$(BIN)/python bench/bench_enhance.py

clean:
	rm -rf $(VENV) .volcap demo .pytest_cache
