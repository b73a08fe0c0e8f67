# The two commands of the README: `make run` and `make test`. Both create the virtualenv
# and install the project first, so they work on a fresh clone.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
CONFIG ?= config/default.toml
# `make smoke`: the wheel, installed (not editable) into a fresh virtualenv of its own.
WHEEL_DIR := build/wheel
SMOKE_VENV := build/smoke-venv

.PHONY: run test smoke lint figures bench fuzz clean

# Byte-compile the sources, as pip does for a regular install: an editable install leaves it to
# the first import, and with PYTHONDONTWRITEBYTECODE=1 (set on these machines) every process
# then compiles each module it imports again (~0.3 s for the calibration and the simulator's
# config, inside the calibration bench's timing).
COMPILE = $(PY) -m compileall -q bridge drivers sim bench > /dev/null

# pip's own output shows what is being downloaded and installed (the first time takes a while).
$(STAMP): pyproject.toml
	@echo "== Setting up $(VENV): a virtualenv with koala-bridge (editable) and its dev and cluster extras"
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e '.[dev,cluster]'
	$(COMPILE)
	touch $(STAMP)
	@echo "== $(VENV) is ready"

run: $(STAMP)
	$(VENV)/bin/koala-bridge run --config $(CONFIG) --clock realtime

# pytest exits 5 when it collected no test; make treats any non-zero exit as failure.
# TEST_WORKERS pytest-xdist workers (the CI machine has two cores), a test file per worker at a
# time (--dist loadfile: a module's fixtures, a simulator recording say, are built once);
# `make test TEST_WORKERS=0` runs the suite in this process, one test after another.
# Then the installed product: packaging cannot break unseen.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile
	$(MAKE) --no-print-directory smoke

# Build the wheel from a clean build folder (setuptools would ship stale files left in
# build/lib), install it as a user does into a fresh virtualenv (dependencies from the pip
# cache; --no-compile: Python compiles what the smoke test imports, not all of scipy), and run
# every subcommand from a temporary directory outside the checkout.
smoke: $(STAMP)
	@echo "== Smoke test of the installed wheel ($(SMOKE_VENV))"
	rm -rf build/lib build/bdist.* $(WHEEL_DIR) $(SMOKE_VENV)
	$(PY) -m pip wheel --quiet --no-deps --wheel-dir $(WHEEL_DIR) .
	$(PYTHON) -m venv $(SMOKE_VENV)
	$(SMOKE_VENV)/bin/python -m pip install --quiet --no-compile $(WHEEL_DIR)/koala_bridge-*.whl
	$(SMOKE_VENV)/bin/python tests/smoke_installed.py

lint: $(STAMP)
	$(VENV)/bin/ruff check bridge drivers sim tests
	$(VENV)/bin/mypy bridge drivers sim

figures: $(STAMP)
	$(PY) -m koala_bridge.tools.figures docs/figures

bench: $(STAMP)
	$(COMPILE)
	$(PY) -m bench

# The soak/fuzz run against a live bridge (bench/fuzz.py; not part of `make test`): tens of
# thousands of bad inputs on every bus; prints crashes, hangs, rejects and peak RSS, and fails
# on a crash or a hang. Larger runs: make fuzz FUZZ_ARGS="--kteam 100000 --seconds 1800".
FUZZ_ARGS ?=
fuzz: $(STAMP)
	$(PY) bench/fuzz.py $(FUZZ_ARGS)

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
