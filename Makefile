# gsmsdr-ns: `make demo` and `make test` create or refresh .venv themselves.
# The stamp file is rebuilt when pyproject.toml changes, so an up-to-date venv costs nothing.

PYTHON ?= python3
# Idle OpenMP threads spin briefly, then sleep: with libgomp's default spin, another busy process on a 2-core machine
# made the blur field's 2-thread backward ~40x slower (7.4 s vs 0.17 s per call at 100x75); sleeping at once
# (OMP_WAIT_POLICY=PASSIVE) costs an idle machine a third of the second thread (docs/design.md, CPU and shared
# machines). A short spin is as good as PASSIVE next to another process and better alone.
export GOMP_SPINCOUNT ?= 1000
VENV := .venv
VENV_PYTHON := $(VENV)/bin/python
STAMP := $(VENV)/.gsmsdr-installed
PYTEST := $(VENV_PYTHON) -m pytest -q -p no:cacheprovider

.PHONY: venv demo lint test test-slow test-all clean-venv

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(VENV_PYTHON) || $(PYTHON) -m venv $(VENV)
	$(VENV_PYTHON) -m pip install -e '.[test,ray]'
	@touch $@

demo: $(STAMP)
	$(VENV_PYTHON) -m gsmsdr_ns.demo

# test: the default suite (pyproject's addopts deselect `slow`); test-slow: long trainings and end-to-end accuracy
# runs only; test-all: both. A slow or heavily shared machine: GSMSDR_TEST_TIMEOUT_SCALE=3 make test (hang guards).
# lint: ruff (lint + format), the layer contracts of pyproject.toml (lint-imports), and mypy on the typed core.
lint: $(STAMP)
	$(VENV)/bin/ruff check gsmsdr_ns tests scripts tools
	$(VENV)/bin/ruff format --check gsmsdr_ns tests scripts tools
	$(VENV)/bin/lint-imports
	$(VENV)/bin/mypy gsmsdr_ns/ops gsmsdr_ns/render gsmsdr_ns/blur

test: lint
	$(PYTEST)

test-slow: $(STAMP)
	$(PYTEST) -m slow

test-all: $(STAMP)
	$(PYTEST) -m 'slow or not slow'

clean-venv:
	rm -rf $(VENV)
