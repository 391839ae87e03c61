"""The pipeline's answers depend on the target, never on its place in the target list: the invert stage's
optimiser runs and the validate stage's posterior draws and refinements are seeded per target (the invert
stage seeded problem n with seed*1000+n; the NPE drew all targets from one torch stream)."""

from __future__ import annotations

import io
import json

SPEC = """
name: stage-determinism
seed: 5
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 120, batch_size: 60}
surrogate: {type: ensemble, members: 2, hidden: [16, 16, 8], max_epochs: 30, patience: 10, dropout: 0.0}
optimizers:
  cma: {type: cma_es, budget: 60, popsize: 6}
  cma_pen: {type: cma_es, budget: 60, popsize: 6, uncertainty_penalty: 0.5}
  npe_opt: {type: npe, max_num_epochs: 4, hidden_features: 8, num_transforms: 1, samples: 8, answer: best_log_prob}
targets: {file: TARGETS, validate: 5}
evaluation:
  baselines:
    nearest_neighbour: {type: nearest_neighbour}
    npe: {type: npe, max_num_epochs: 4, hidden_features: 8, num_transforms: 1, samples: 8, answer: mean}
  methods:
    pen_nn: {start: nearest_neighbour, evaluator: surrogate, budget: 30, popsize: 6, uncertainty_penalty: 0.5}
validator: {type: simulator, batch_size: 64}
stages: [dataset, train, invert, validate]
"""


def _run(out, targets_file, stages):
    import yaml
    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    spec = yaml.safe_load(SPEC.replace("TARGETS", str(targets_file)))
    if targets_file is None:  # the dataset alone (the targets are made from it)
        spec["targets"] = {"n": 2, "validate": 0}
    run_spec(validate_spec(spec), out, stages=stages, progress=False, console=Console(file=io.StringIO()))


def _answers(out):
    """{(label, target features): theta} of the invert stage's and the evaluation's target rows."""
    targets = json.loads((out / "invert" / "targets.json").read_text())["features"]
    rows = json.loads((out / "invert" / "results.json").read_text())
    rows += json.loads((out / "validate" / "evaluation_rows.json").read_text())
    return {(r["optimizer"], tuple(targets[r["target_index"]])): r["theta"] for r in rows if r["problem"] == "target"}


def test_stage_answers_do_not_depend_on_the_target_order(tmp_path) -> None:
    from invphys.core.dataset import DatasetStore

    out = tmp_path / "run"
    fwd, rev = tmp_path / "fwd.json", tmp_path / "rev.json"
    _run(out, None, ["dataset"])
    data = DatasetStore(out / "dataset" / "store").arrays()
    rows = [dict(zip(data.feature_names, map(float, y), strict=True)) for y in data.y[-5:]]
    fwd.write_text(json.dumps(rows))
    rev.write_text(json.dumps(rows[::-1]))
    _run(out, fwd, ["dataset", "train", "invert", "validate"])
    a = _answers(out)
    _run(out, rev, ["dataset", "train", "invert", "validate"])
    b = _answers(out)
    labels = {label for label, _ in a}
    assert labels == {"cma", "cma_pen", "npe_opt", "nearest_neighbour", "npe", "pen_nn"} and len(a) == 30
    assert a.keys() == b.keys()
    assert sorted({label for label, t in a if a[(label, t)] != b[(label, t)]}) == []


def test_stage_keys_carry_the_seeding_so_older_cached_answers_re_run() -> None:
    """Stages that make answers (invert, validate, active) record how answers are seeded: a stage cached by
    an invphys that seeded by position is re-run (and says why) instead of serving answers this one would
    not give; stages that make none keep their keys."""
    import yaml

    from invphys.core.spec import validate_spec
    from invphys.pipeline import cache
    from invphys.pipeline.stages import invert, train, validate
    from invphys.registry import default_registry

    spec = validate_spec(yaml.safe_load(SPEC.replace("TARGETS", "t.json").replace(
        "targets: {file: t.json, validate: 5}", "targets: {n: 2}")))
    reg = default_registry()
    for module in (invert, validate):
        assert cache.plugin_versions(spec, module.DEPENDS_ON, reg)[cache.SEEDING_ENTRY] == cache.SEEDING
    assert cache.SEEDING_ENTRY not in cache.plugin_versions(spec, train.DEPENDS_ON, reg)
    now = {"spec": "s", "plugins": cache.plugin_versions(spec, invert.DEPENDS_ON, reg)}
    before = {"components": {"spec": "s", "plugins": {k: v for k, v in now["plugins"].items()
                                                      if k != cache.SEEDING_ENTRY}}}
    assert cache.stale_reason(before, now) == "how answers are seeded (now per target, not by position) changed"
