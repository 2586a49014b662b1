# The two commands (see README): `make run` runs a scenario, `make test` runs the test suite.
# Both set up a virtual environment in .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
SCENARIO ?= scenarios/two_cubes.yaml

.PHONY: run test lint bench setup

$(BIN)/dynabrain: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

setup: $(BIN)/dynabrain

run: setup
	$(BIN)/dynabrain run $(SCENARIO)

test: setup
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

bench: setup
	for b in bench/*.py; do $(BIN)/python $$b || exit 1; done
