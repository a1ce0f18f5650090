# gsmsdr-ns: `make demo` and `make test` create or refresh .venv themselves.
# The stamp file is rebuilt when pyproject.toml changes, so an up-to-date venv costs nothing.

PYTHON ?= python3
VENV := .venv
VENV_PYTHON := $(VENV)/bin/python
STAMP := $(VENV)/.gsmsdr-installed
PYTEST := $(VENV_PYTHON) -m pytest -q -p no:cacheprovider

.PHONY: venv demo test test-slow clean-venv

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(VENV_PYTHON) || $(PYTHON) -m venv $(VENV)
	$(VENV_PYTHON) -m pip install -e '.[test]'
	@touch $@

demo: $(STAMP)
	$(VENV_PYTHON) -m gsmsdr_ns.demo

test: $(STAMP)
	$(PYTEST)

test-slow: $(STAMP)
	$(PYTEST) -m slow

clean-venv:
	rm -rf $(VENV)
