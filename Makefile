# The two commands of the README: `make run` and `make test`. Both create the virtualenv
# and install the project first, so they work on a fresh clone.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
CONFIG ?= config/default.toml

.PHONY: run test lint figures bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/koala-bridge run --config $(CONFIG) --clock realtime

# pytest exits 5 when it collected no test; make treats any non-zero exit as failure.
test: $(STAMP)
	$(PY) -m pytest -q

lint: $(STAMP)
	$(VENV)/bin/ruff check bridge drivers sim tests
	$(VENV)/bin/mypy bridge drivers sim

figures: $(STAMP)
	$(PY) -m koala_bridge.tools.figures docs/figures

bench: $(STAMP)
	$(PY) -m bench

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
