"""The cheese cut's whole pipeline (dataset -> train -> invert -> validate -> report) at its tiny preset on a
CPU, from the spec shipped inside the package: real simulations, real training, real validation runs."""

from __future__ import annotations

import json
from importlib.resources import files

import pytest

pytest.importorskip("taichi")
pytest.importorskip("torch")
pytest.importorskip("cma")

import invphys


def test_tiny_spec_runs_the_whole_pipeline(tmp_path) -> None:
    spec = files("invphys_cheese_cut") / "specs" / "tiny.yaml"
    assert spec.is_file()  # shipped as package data
    invphys.run(invphys.load_spec(str(spec)), tmp_path / "run")
    out = tmp_path / "run"
    validation = json.loads((out / "validate" / "validation.json").read_text())
    assert len(validation) >= 2
    assert all(v["failure"] is None for v in validation)
    assert all(-1.0 <= v["r_actual"] <= 1.0 for v in validation)
    report = json.loads((out / "report" / "report.json").read_text())
    text = json.dumps(report)
    assert "cma_es" in text and "nearest_neighbour" in text
    assert (out / "report" / "report.md").stat().st_size > 500
