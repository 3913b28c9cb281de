# Two commands do all the set-up: `make run` and `make test` (each creates or reuses .venv).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: venv install lint run test test-slow test-learning test-all bench clean

venv: $(STAMP)

# torch first (the pinned CPU build; an unpinned torch would pull a multi-GB CUDA build),
# then the project with its dev extra.
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[dev]"
	$(PY) -m mam_core.gemm  # portable arithmetic's GEMM kernels, built with the C compiler (cc)
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(VENV)/bin/mam run --config deploy/demo.toml $(RUN_ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .

# The fast suite on TEST_WORKERS processes (pytest-xdist; each idle one takes the next test):
# on a 2-core box 2 took 0.63x the time of 1 (docs/PERFORMANCE.md, "The test suites").
TEST_WORKERS ?= 2
test: $(STAMP) lint
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist worksteal

# One line per test as it ends (-v, unbuffered: a CI log cut short still names the test that ran
# last), the slowest listed, and no new test started after 60 minutes (CI stops at 90); two at a
# time like the fast suite (each test's processes wait on each other much of the time).
test-slow: $(STAMP)
	PYTHONUNBUFFERED=1 $(PY) -m pytest -v -n $(TEST_WORKERS) --dist worksteal --durations=15 --session-timeout=3600 \
		-m "slow and not learning"

test-learning: $(STAMP)
	$(PY) -m pytest -q -m learning

test-all: $(STAMP)
	$(PY) -m pytest -q -m "slow or not slow"

bench: $(STAMP)
	$(VENV)/bin/mam bench $(BENCH_ARGS)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
