# SlipMap — the two commands of the README are `make demo` and `make test`.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
NP2 := .venv-np2/bin/python
PYTEST_ARGS ?=

.PHONY: setup setup-main demo test test-main test-np2 test-debian13 lint format bench plugin-zip clean

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

# The README's two commands again in a Debian 13 root (QGIS 3.40, numpy 2, Python 3.13), built
# with debootstrap into ~/.cache/slipmap-debian13 (SLIPMAP_DEBIAN13_CACHE); needs root or sudo.
# Not part of `make test`. scripts/debian13.sh shell|run CMD|clean for more.
test-debian13:
	PYTEST_ARGS="$(PYTEST_ARGS)" bash scripts/debian13.sh test

bench: setup-main
	$(PY) benchmarks/bench_planes.py --n 1000000

plugin-zip:
	bash scripts/plugin_zip.sh

clean:
	rm -rf build dist *.egg-info .pytest_cache .ruff_cache demo_output slipmap-*.zip
