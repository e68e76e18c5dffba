# Two-command entry: `make run` (main job on the embedded R6 + packaged bench data)
# and `make test` (the test suite).  Both create .venv and install on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

# Keep Prefect quiet, offline and inside the project (docs/stack.md).
export PREFECT_HOME := $(CURDIR)/.prefect
export DO_NOT_TRACK := 1
export PREFECT_SERVER_ANALYTICS_ENABLED := false
export PREFECT_LOGGING_LEVEL := WARNING
export PREFECT_SERVER_LOGGING_LEVEL := CRITICAL
export PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS := 60

.PHONY: run test test-fast bench install clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

run: $(STAMP)
	$(BIN)/mbc run

# Two pytest-xdist workers (CI has 2 cores): each test module is one group and runs on one worker, so its
# module fixtures are built once; the tests of the shared quick run form one group (tests/conftest.py).
XDIST := -n 2 --dist loadgroup

test: $(STAMP)
	$(BIN)/python -m pytest $(XDIST)

test-fast: $(STAMP)
	$(BIN)/python -m pytest $(XDIST) -m "not slow and not integration"

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_cycle.py

clean:
	rm -rf $(VENV) .prefect .pytest_cache
