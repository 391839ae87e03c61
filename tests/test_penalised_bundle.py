"""A penalised CMA-ES ships in a bundle: the manifest's method entry keeps the spec's ``uncertainty_penalty``
(and, for an ``evaluation.methods`` refinement on the surrogate, its ``start``), and `invphys invert --method`
answers every target exactly as the pipeline's invert (or validate) stage did for the same target and seed.
Before, the export dropped both and the bundle answered with a plain CMA-ES."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

SPEC = """
name: penalised-bundle
seed: 7
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 120, batch_size: 60}
surrogate: {type: ensemble, members: 2, hidden: [16, 16, 8], max_epochs: 30, patience: 10, dropout: 0.0}
optimizers:
  cma_pen: {type: cma_es, budget: 60, popsize: 6, sigma0: 0.2, uncertainty_penalty: 2.0}
  lookup: {type: nearest_neighbour}
targets: {n: 4, validate: 4}
evaluation:
  baselines: {}
  methods:
    pen_lookup: {start: lookup, evaluator: surrogate, budget: 30, popsize: 6, sigma0: 0.1, uncertainty_penalty: 2.0}
validator: {type: simulator, batch_size: 64}
stages: [dataset, train, invert, validate]
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    out = tmp_path_factory.mktemp("penalised") / "run"
    run_spec(validate_spec(yaml.safe_load(SPEC)), out, progress=False, console=Console(file=io.StringIO()))
    targets = json.loads((out / "invert" / "targets.json").read_text())
    rows = json.loads((out / "invert" / "results.json").read_text())
    rows += json.loads((out / "validate" / "evaluation_rows.json").read_text())
    return out, targets, rows


def _cli(bundle, targets, method, tmp_path, seed=7):
    from invphys.cli import app

    f = tmp_path / f"targets_{method}.json"
    f.write_text(json.dumps([dict(zip(targets["feature_names"], y, strict=True)) for y in targets["features"]]))
    res = CliRunner().invoke(app, ["invert", str(bundle), "--target", str(f), "--method", method, "--json",
                                   "--seed", str(seed)])
    assert res.exit_code == 0, res.output
    return [r["candidates"][0]["theta"] for r in json.loads(res.stdout)["results"]]


def _stage(rows, label):
    mine = sorted((r for r in rows if r["optimizer"] == label and r["problem"] == "target"),
                  key=lambda r: r["target_index"])
    return [r["theta"] for r in mine]


def test_the_manifest_keeps_the_penalty_and_the_start(run) -> None:
    out, _, _ = run
    methods = yaml.safe_load((out / "inverter" / "manifest.yaml").read_text())["methods"]
    assert methods["cma_pen"]["uncertainty_penalty"] == 2.0 and "uncertainty_penalty" not in methods["cma_pen"]["config"]
    assert "uncertainty_penalty" not in methods["lookup"]
    ref = methods["pen_lookup"]
    assert ref["start"] == "lookup" and ref["uncertainty_penalty"] == 2.0 and ref["type"] == "cma_es"
    assert ref["config"] == {"budget": 30, "popsize": 6, "sigma0": 0.1}


def test_the_bundle_answers_as_the_stages_did(run, tmp_path) -> None:
    out, targets, rows = run
    for label in ("cma_pen", "pen_lookup"):
        assert _cli(out / "inverter", targets, label, tmp_path) == _stage(rows, label), label


def test_a_bundle_without_the_keys_answers_as_before(run, tmp_path) -> None:
    """An older bundle's entry (no uncertainty_penalty) is a plain CMA-ES: other answers than the penalised."""
    import shutil

    out, targets, rows = run
    old = tmp_path / "old"
    shutil.copytree(out / "inverter", old)
    manifest = yaml.safe_load((old / "manifest.yaml").read_text())
    del manifest["methods"]["cma_pen"]["uncertainty_penalty"]
    (old / "manifest.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    plain = _cli(old, targets, "cma_pen", tmp_path)
    assert plain != _stage(rows, "cma_pen")
    import invphys

    inv = invphys.load_inverter(old)
    got = [inv.invert(np.asarray(y), method="cma_pen", seed=7).theta.tolist() for y in targets["features"]]
    assert got == plain
