"""The invert, validate and report stages end to end on a fast real simulator (the toy oscillator)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import yaml

SPEC = """
name: optim-stages
seed: 3
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 160, batch_size: 40}
surrogate: {type: mlp, hidden: [32, 32, 16], max_epochs: 80, patience: 20, dropout: 0.0}
latent_models:
  flow: {type: realnvp, latent_dim: 2, max_epochs: 10}
optimizers:
  cma: {type: cma_es, budget: 200}
  ng: {type: nevergrad, optimizer: OnePlusOne, budget: 100}
  cma_flow: {type: cma_es, space: flow, budget: 100}
  cma_head: {type: cma_es, space: flow, evaluator: own_head, budget: 100}
  ppo: {type: ppo, total_timesteps: 512, n_steps: 64, n_envs: 4, net_arch: [16, 16]}
  gc: {type: gc_ppo, total_timesteps: 1024, n_steps: 64, n_envs: 4, net_arch: [32, 32]}
  ws: {type: warm_start, policy: gc, budget: 60}
objectives:
  lively: {weights: {peak_abs: 1.0, log_decay: 1.0}}
targets: {n: 4, validate: 2}
validator: {type: simulator}
report: {render: true}
"""


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out = tmp_path_factory.mktemp("run")
    spec = parse_spec(SPEC)
    events: list[tuple[str, str]] = []
    run_spec(spec, out, progress=False, console=Console(file=io.StringIO()),
             on_stage=lambda s, status, _: events.append((s, status)))
    return out, spec, events


def test_invert_runs_every_entry_on_targets_and_objectives(run_dir) -> None:
    out, _, events = run_dir
    assert [s for s, st in events if st == "done"] == ["dataset", "train", "invert", "validate", "report"]
    rows = json.loads((out / "invert" / "results.json").read_text())
    targets = json.loads((out / "invert" / "targets.json").read_text())
    assert len(targets["rows"]) == 4 and targets["selection"] == "farthest_point"
    count = {}
    for r in rows:
        count[(r["optimizer"], r["problem"])] = count.get((r["optimizer"], r["problem"]), 0) + 1
        assert r["evaluations"] == r["counted_evaluations"]  # what the optimiser reports is what it spent
        assert 0.0 <= min(r["theta"]) and max(r["theta"]) <= 1.0
    assert count == {("cma", "target"): 4, ("cma", "objective"): 1, ("ng", "target"): 4, ("ng", "objective"): 1,
                     ("cma_flow", "target"): 4, ("cma_flow", "objective"): 1, ("cma_head", "target"): 4,
                     ("cma_head", "objective"): 1, ("ppo", "objective"): 1, ("gc", "target"): 4,
                     ("ws", "target"): 4}
    by = {(r["optimizer"], r["problem_id"]): r for r in rows}
    assert all(by[("cma", f"t{k:02d}")]["evaluations"] == 200 for k in range(4))
    assert all(by[("gc", f"t{k:02d}")]["evaluations"] == 8 for k in range(4))
    assert all(by[("ws", f"t{k:02d}")]["evaluations"] == 40 + 60 for k in range(4))
    assert by[("cma_flow", "t00")]["space"] == "flow" and len(by[("cma_flow", "t00")]["point"]) == 2
    assert by[("ws", "t00")]["space"] == "raw"  # the warm start borrows its policy's space
    assert by[("cma_head", "t00")]["evaluator"] == "own_head"
    assert by[("ppo", "lively")]["evaluations"] == 1 + 512 + 8
    # the cached policy is saved in the stage directory
    assert (out / "invert" / "policies" / "gc" / "policy.npz").is_file()
    # CMA-ES with 200 evaluations beats the policy's 8 evaluations on average
    mean = {k: np.mean([by[(k, f"t{i:02d}")]["r_surrogate"] for i in range(4)]) for k in ("cma", "gc")}
    assert mean["cma"] >= mean["gc"]


def test_validate_re_simulates_recovered_parameters(run_dir) -> None:
    from test_dataset_toy import ToyFeatures, ToyOscillator

    from invphys.core.objectives import recovery_reward

    out, _, _ = run_dir
    val = json.loads((out / "validate" / "validation.json").read_text())
    targets = json.loads((out / "invert" / "targets.json").read_text())
    # the first 2 targets of the 6 target-solving entries, and the 5 objective rows; the evaluation's
    # default baselines (nearest_neighbour, npe) and the noise floor are validated beside them
    assert sum(v["problem"] == "target" and v.get("role", "optimizer") == "optimizer" for v in val) == 12
    assert sum(v["problem"] == "target" for v in val) == 12 + 3 * 2
    assert {v["target_index"] for v in val if v["problem"] == "target"} == {0, 1}
    assert sum(v["problem"] == "objective" for v in val) == 5
    sim, ext = ToyOscillator(), ToyFeatures()
    scales = np.asarray(targets["scales"])
    for v in [v for v in val if v["problem"] == "target"][:3]:
        direct = sim.simulate(sim.parameter_space().denormalize(np.asarray(v["theta"])[None]))[0]
        if not direct.ok:
            assert v["failure"]
            continue
        feats = ext.extract(direct.trajectory)
        np.testing.assert_allclose(v["actual"], feats)
        y_star = np.asarray(targets["features"][v["target_index"]])
        assert v["r_actual"] == pytest.approx(float(recovery_reward(feats, y_star, scales)))
        assert v["gap"] == pytest.approx(v["r_surrogate"] - v["r_actual"])
    assert (out / "validate" / "renders" / "t00_target.npz").is_file()


def test_report_writes_tables_plot_and_renders_and_reruns_are_cached(run_dir) -> None:
    from rich.console import Console

    from invphys.pipeline.runner import run_spec

    out, spec, _ = run_dir
    md = (out / "report" / "report.md").read_text()
    assert "| optimizer | evaluations | R_surr | R_actual | Delta | time (s) | note |" in md
    assert "### Target 3" in md and "not validated" in md and "## Named objectives" in md
    assert "![recovery](recovery.png)" in md and "renders/t00.png" in md
    assert (out / "report" / "recovery.png").stat().st_size > 10_000
    assert (out / "report" / "renders" / "t00.png").is_file()
    rep = json.loads((out / "report" / "report.json").read_text())
    summ = {s["optimizer"]: s for s in rep["summary"]}
    assert summ["cma"]["validated"] == 2 and summ["gc"]["evaluations"] == 8
    assert summ["cma"]["r_actual"] is None or 0.0 <= summ["cma"]["r_actual"] <= 1.0
    import pandas as pd

    csv = pd.read_csv(out / "report" / "report.csv")
    # 29 optimiser rows, the 2 default baselines on 4 targets, the noise floor on the 2 validated ones
    assert len(csv) == len(rep["rows"]) == 29 + 4 * 2 + 2 and {"r_surrogate", "r_actual", "gap"} <= set(csv.columns)
    events: list[tuple[str, str]] = []
    run_spec(spec, out, progress=False, console=Console(file=io.StringIO()),
             on_stage=lambda s, status, _: events.append((s, status)))
    assert all(st == "cached" for _, st in events) and len(events) == 5
    # own-head rows: R_surr is scored on the flow's head, R_actual on the simulator
    val = json.loads((out / "validate" / "validation.json").read_text())
    head = [v for v in val if v["optimizer"] == "cma_head" and v["problem"] == "target"]
    assert len(head) == 2 and all(np.isfinite(v["r_surrogate"]) for v in head)
    # a bad policy label is a clear error
    from invphys.core.errors import InvphysError
    from invphys.core.spec import parse_spec

    bad = yaml.safe_load(SPEC)
    bad["optimizers"]["ws"]["policy"] = "cma"
    bad["stages"] = ["invert"]
    with pytest.raises(InvphysError, match="not a goal-conditioned entry"):
        run_spec(parse_spec(yaml.safe_dump(bad)), out, progress=False, console=Console(file=io.StringIO()))


def test_a_cached_policy_in_the_older_pickled_format_is_trained_again_not_unpickled(run_dir, tmp_path,
                                                                                      caplog) -> None:
    """A run directory made before pickle-free saves holds only SB3's policy.zip: the invert stage trains the
    policy again (before, loading it stopped the stage with exit 2); the zip is never read."""
    import shutil

    from rich.console import Console

    from invphys.pipeline.runner import run_spec

    out, spec, _ = run_dir
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    cache = copy / "invert" / "policies" / "gc"
    (cache / "policy.npz").unlink()
    (cache / "policy.zip").write_bytes(b"an old cloudpickled zip: never read")
    (copy / "invert" / "DONE.json").unlink()
    with caplog.at_level("INFO", logger="invphys.pipeline.stages"):
        run_spec(spec, copy, stages=["invert"], progress=False, console=Console(file=io.StringIO()))
    assert "older pickled format; training it again" in caplog.text
    assert (cache / "policy.npz").is_file()
