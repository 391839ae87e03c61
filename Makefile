# Everything a fresh machine needs: `make demo` (the orange-peel quick start) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test lint typecheck docs unit bench-cpu clean

setup: $(STAMP)

$(STAMP): pyproject.toml examples/orange_peel/pyproject.toml examples/anisompm/pyproject.toml examples/cheese_cut/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -U pip setuptools wheel
	# the CPU build of torch first, so that nothing pulls a CUDA build
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e ".[all]" -e examples/orange_peel -e examples/anisompm -e examples/cheese_cut
	touch $(STAMP)

demo: setup
	$(BIN)/invphys run examples/orange_peel/invphys_orange_peel/specs/quickstart.yaml --out runs/quickstart

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
