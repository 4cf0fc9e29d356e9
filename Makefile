# FluoGuide: the two commands of README.md.
#   make demo   set up .venv and run the main job (the end-to-end demo on the digital
#               phantoms, laptop-sized: fluo demo --quick; make demo-full for the study)
#   make test   set up .venv if needed and run the whole test suite
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_OUT ?= demo-out

.PHONY: demo demo-full demo-quick test test-fast bench docs venv clean system-deps

venv: $(STAMP)

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip>=24"
	$(PY) -m pip install --quiet -c constraints.txt -e ".[test,mc]"
	touch $(STAMP)

# the demo on every core (a laptop running it is otherwise quiet; on a 2-core machine
# the quick demo takes three quarters of its one-thread time, docs/performance.md);
# make demo DEMO_THREADS=1 for a busy machine
DEMO_THREADS ?= auto

demo: $(STAMP)
	$(VENV)/bin/fluo --threads $(DEMO_THREADS) demo --quick --out $(DEMO_OUT)

demo-quick: demo

# the whole study (five tube depths at the balanced level): a workstation's memory
demo-full: $(STAMP)
	$(VENV)/bin/fluo --threads $(DEMO_THREADS) demo --out $(DEMO_OUT)

# one thread per library, as the fluo CLI's default (docs/performance.md): on a busy
# 2-core machine the libraries' own defaults ran a reconstruction 7-11x slower
TEST_THREADS := OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1
# numba's compiled kernels, cached once for every process of a run (test
# workers, fork-server children, subprocesses) and for the next run
NUMBA_CACHE := NUMBA_CACHE_DIR=$(CURDIR)/$(VENV)/numba-cache
# test processes side by side (pytest-xdist), whole files each, in conftest.py's
# order (heavy and slow files first; docs/DEVELOPING.md, "The test suite");
# JOBS=1 runs them in one process
JOBS ?= 2
XDIST = $(if $(filter 1,$(JOBS)),-p no:xdist,-n $(JOBS) --dist loadfile --no-loadscope-reorder)

# Debian packages the tests need (Chromium, cmake, pocl, Qt's offscreen libraries):
# installed when missing, or one line naming the command that installs them
system-deps:
	@bash .ci/system-deps.sh

# the whole suite: every test runs (none skipped for a missing package); the 30
# slowest and every skipped test with its reason are printed at the end
test: system-deps $(STAMP)
	$(TEST_THREADS) $(NUMBA_CACHE) $(PY) -m pytest -q $(XDIST) --durations=30

test-fast: $(STAMP)
	$(TEST_THREADS) $(NUMBA_CACHE) $(PY) -m pytest -q $(XDIST) -m "not slow and not browser"

bench: $(STAMP)
	$(PY) -m benchmarks

# the API reference from the docstrings (docs/api), every Sphinx warning an error,
# as Testing/Python/test_api_reference.py builds it in CI; open build/docs/index.html
docs: $(STAMP)
	$(TEST_THREADS) $(PY) -m sphinx -W --keep-going -b html docs/api build/docs

clean:
	rm -rf $(VENV) build *.egg-info $(DEMO_OUT) test-artifacts
