# Two set-up commands on a fresh machine: `make demo` and `make test`. Each creates what it
# needs (a local .venv, the Debian packages for the GUI tests) and works from a clean clone.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
export DSLRXR_DATA ?= $(abspath ../shared/data)

.PHONY: demo test test-core bench system-deps clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip setuptools wheel

# One pinned environment (requirements/test-constraints.txt) for the demo, the tests and CI.
CONSTRAINTS := requirements/test-constraints.txt

$(VENV)/.installed-core: pyproject.toml $(CONSTRAINTS) | $(BIN)/python
	$(BIN)/python -m pip install -q -c $(CONSTRAINTS) -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml $(CONSTRAINTS) | $(BIN)/python
	$(BIN)/python -m pip install -q -c $(CONSTRAINTS) -e '.[test]'
	touch $@ $(VENV)/.installed-core

system-deps:
	@bash scripts/install-system-deps.sh

demo: $(VENV)/.installed-core
	$(BIN)/python -m napari_dslrxr.demo demo_output

# -n auto: one pytest worker per core (pytest-xdist); each GUI worker gets its own virtual display
test: $(VENV)/.installed-test system-deps
	$(BIN)/python -m pytest -n auto

# Headless core only: no display, no Qt.
test-core: $(VENV)/.installed-test
	$(BIN)/python -m pytest -n auto -m "not gui" -p no:xvfb

bench: $(VENV)/.installed-test
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) demo_output .pytest_cache build *.egg-info src/*.egg-info
