# The two commands (see README): `make run` runs a scenario, `make test` runs the test suite.
# Both set up a virtual environment in .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
SCENARIO ?= scenarios/two_cubes.yaml

.PHONY: run test lint bench bench-peers setup system-deps

# Offscreen rendering for the camera module (EGL with Mesa). Installed when missing and we are root
# (as in CI); otherwise a note, and the camera says at load that no renderer works.
EGL_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri
# Headless Chromium for the test that opens the Rerun web viewer (tests/test_view_rerun.py), the same way.
BROWSER_PACKAGES := chromium
system-deps:
	@if ldconfig -p | grep -q 'libEGL.so.1 '; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(EGL_PACKAGES) >/dev/null) \
	  || echo "note: could not install $(EGL_PACKAGES); camera tests will skip"; \
	else echo "note: $(EGL_PACKAGES) are not installed; camera tests will skip"; fi
	@if command -v chromium >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $(BROWSER_PACKAGES) >/dev/null) \
	  || echo "note: could not install $(BROWSER_PACKAGES); the Rerun viewer's browser test will skip"; \
	else echo "note: $(BROWSER_PACKAGES) is not installed; the Rerun viewer's browser test will skip"; fi

$(BIN)/dynabrain: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $@

setup: system-deps $(BIN)/dynabrain

run: setup
	$(BIN)/dynabrain run $(SCENARIO)

# The suite runs on every core up to four (pytest-xdist), one test file per worker at a time so a file's
# module fixtures (FMU builds, tick runners) are made once: on 2 cores 92 s instead of 152 s.
test: setup
	$(BIN)/ruff check .
	$(BIN)/lint-imports --no-cache
	$(BIN)/python -m pytest -q -n auto --maxprocesses 4 --dist loadfile

bench: setup
	@all=$$(ls bench/*.py | grep -v timing.py); n=$$(echo "$$all" | wc -l); i=0; t0=$$(date +%s); \
	for b in $$all; do i=$$((i + 1)); \
	  echo "== [$$i/$$n] $$b ($$(( $$(date +%s) - t0 )) s so far)"; $(BIN)/python $$b || exit 1; done; \
	echo "== $$n benchmarks in $$(( $$(date +%s) - t0 )) s"

# The FMU masters bench/fmu_chain.py compares with (ecos and libcosim, from PyPI), and the TBB runtime
# ecos's library needs (installed when missing and we are root; otherwise a note). Not needed by tests.
PEERS := ecospy==0.7.2 libcosimpy==0.0.6
bench-peers: setup
	@if ldconfig -p | grep -q 'libtbb.so.12 '; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libtbb12 >/dev/null) \
	  || echo "note: could not install libtbb12; ecos will not run"; \
	else echo "note: libtbb12 is not installed; ecos will not run"; fi
	$(BIN)/pip install --quiet $(PEERS)
	@$(BIN)/pip install --quiet omsimulator \
	  || echo "note: omsimulator did not install (its install downloads OpenModelica's binaries); the bench skips it"
	$(BIN)/python bench/fmu_chain.py
