# SlipMap — the two commands of the README are `make demo` and `make test`.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
NP2 := .venv-np2/bin/python
PYTEST_ARGS ?=

.PHONY: setup setup-main demo test test-main test-np2 lint format bench plugin-zip clean

setup:
	@bash scripts/setup_env.sh all

setup-main:
	@bash scripts/setup_env.sh main

demo: setup-main
	$(VENV)/bin/slipmap demo --out demo_output

lint: setup-main
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: setup-main
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

# Whole suite in the Debian venv (QGIS, GDAL, PyOpenCL/PoCL present), then the core, I/O and CLI
# tests again in a plain PyPI venv with numpy >= 2 (no QGIS there).
test: setup lint test-main test-np2

test-main:
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest $(PYTEST_ARGS)

test-np2:
	$(NP2) -c "import numpy; assert int(numpy.__version__.split('.')[0]) >= 2, numpy.__version__"
	$(NP2) -m pytest -m "not qgis" $(PYTEST_ARGS)

bench: setup-main
	$(PY) benchmarks/bench_planes.py --n 1000000

plugin-zip:
	bash scripts/plugin_zip.sh

clean:
	rm -rf build dist *.egg-info .pytest_cache .ruff_cache demo_output slipmap-*.zip
