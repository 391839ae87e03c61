# Everything a fresh machine needs: `make demo` (the orange-peel demo, a few minutes) and `make test`;
# `make demo-full` runs the full quick start (10-20 minutes on 2 cores).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo demo-full test lint typecheck docs unit bench-cpu clean

setup: $(STAMP)

$(STAMP): pyproject.toml examples/orange_peel/pyproject.toml examples/anisompm/pyproject.toml examples/cheese_cut/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -U pip setuptools wheel
	# the CPU build of torch first, so that nothing pulls a CUDA build
	$(BIN)/python -m pip install -q torch==2.13.0
	# the user extras (all), the team's tools (dev), the AnisoMPM engine and the example plugins
	$(BIN)/python -m pip install -q -e ".[all,dev]" -e examples/anisompm -e examples/orange_peel -e examples/cheese_cut
	touch $(STAMP)

demo: setup
	$(BIN)/invphys run examples/orange_peel/invphys_orange_peel/specs/quickstart.yaml --out runs/quickstart

demo-full: setup
	$(BIN)/invphys run examples/orange_peel/invphys_orange_peel/specs/quickstart_full.yaml --out runs/quickstart_full

lint: setup
	$(BIN)/ruff check invphys examples tests benchmarks

typecheck: setup
	$(BIN)/mypy

docs: setup
	$(BIN)/mkdocs build --strict --site-dir site

unit: setup
	$(BIN)/pytest -q -n 2 --durations=15

test: lint typecheck docs unit

bench-cpu: setup
	$(BIN)/python benchmarks/bench_simulator.py --preset tiny --backend taichi

clean:
	rm -rf site runs .pytest_cache .mypy_cache .ruff_cache
