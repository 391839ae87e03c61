"""The evaluation protocol end to end on a fast real simulator (the toy oscillator): baselines in the
report, bootstrap intervals, paired differences, the simulator in the loop, the uncertainty penalty,
recovered parameters and report.json's machine-readable shape."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

SPEC = """
name: eval-protocol
seed: 3
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 200, batch_size: 50}
surrogate: {type: ensemble, members: 2, hidden: [32, 32, 16], max_epochs: 60, patience: 20, dropout: 0.0}
optimizers:
  cma: {type: cma_es, budget: 100}
targets: {n: 8, validate: 8, selection: farthest_point+random}
evaluation:
  baselines:
    nearest_neighbour: {type: nearest_neighbour}
    nn5: {type: nearest_neighbour, k: 5, select: surrogate}
    npe: {type: npe, max_num_epochs: 8, hidden_features: 16, num_transforms: 2, samples: 16}
  methods:
    sil: {start: nearest_neighbour, evaluator: simulator, budget: 9, popsize: 4}
    cma_pen: {start: nearest_neighbour, evaluator: surrogate, budget: 60, popsize: 6, uncertainty_penalty: 0.5}
  bootstrap: 200
validator: {type: simulator, batch_size: 64}
active: {rounds: 2, targets: 4, budget: 60, popsize: 6, max_epochs: 30, uncertainty_penalty: 0.2}
report: {render: false}
"""

FIELDS = ("n_validated", "r_actual_mean", "r_actual_ci95", "r_surrogate_mean", "gap_mean", "evaluations",
          "simulator_runs", "vs_nearest_neighbour")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out = tmp_path_factory.mktemp("protocol")
    spec = parse_spec(SPEC)
    summaries = run_spec(spec, out, progress=False, console=Console(file=io.StringIO()))
    return out, summaries


def test_report_json_has_the_protocol_shape_with_baselines(run_dir) -> None:
    out, _ = run_dir
    rep = json.loads((out / "report" / "report.json").read_text())
    opt = rep["optimizers"]
    assert set(opt) == {"cma", "nearest_neighbour", "nn5", "npe", "sil", "cma_pen", "noise_floor", "active_learning"}
    for label, s in opt.items():
        assert all(f in s for f in FIELDS), label
        assert s["n_validated"] == (4 if label == "active_learning" else 8)
        lo, hi = s["r_actual_ci95"]
        assert lo <= s["r_actual_mean"] <= hi
        assert set(s["by_set"]) == {"farthest_point", "random"}
        assert s["by_set"]["farthest_point"]["n_validated"] == 4  # active learning: the 4 farthest-point ones
    assert opt["nearest_neighbour"]["vs_nearest_neighbour"] is None
    d = opt["cma"]["vs_nearest_neighbour"]
    assert d["n"] == 8 and d["ci95"][0] <= d["mean_diff"] <= d["ci95"][1]
    assert d["beats"] == (d["ci95"][0] > 0)
    # the toy simulator is deterministic: re-simulating the true parameters recovers the target exactly
    assert opt["noise_floor"]["r_actual_mean"] > 0.999
    assert opt["nearest_neighbour"]["evaluations"] == 0 and opt["nn5"]["evaluations"] == 5
    assert opt["npe"]["role"] == "baseline" and opt["sil"]["role"] == "method"
    assert rep["protocol"]["sets"] == {"farthest_point": 4, "random": 4}
    assert (out / "report" / "protocol.png").stat().st_size > 10_000
    md = (out / "report" / "report.md").read_text()
    assert "## Protocol" in md and "## Recovered parameters" in md and "nearest_neighbour" in md


def test_simulator_in_the_loop_never_loses_to_its_start_and_batches_generations(run_dir) -> None:
    out, summaries = run_dir
    info = summaries["validate"]["evaluation"]["sil"]
    # 8 targets x 9 runs; the starts in one batch, then two generations of 4 per target, each one batch
    assert info["simulator_runs"] == 72 and info["batches"] == 3
    rows = json.loads((out / "validate" / "validation.json").read_text())
    by = {(r["optimizer"], r["target_index"]): r for r in rows if r["problem"] == "target"}
    for k in range(8):
        sil, nn = by[("sil", k)], by[("nearest_neighbour", k)]
        assert sil["simulator_runs"] == 9
        assert sil["r_actual"] >= nn["r_actual"] - 1e-12  # its start was simulated too
    ev = {(r["optimizer"], r["target_index"]): r for r in json.loads((out / "validate" / "evaluation_rows.json").read_text())}
    # the loop's own score is the validated R_actual (no reality gap by construction)
    assert all(abs(ev[("sil", k)]["in_loop_score"] - by[("sil", k)]["r_actual"]) < 1e-9 for k in range(8))


def test_recovered_parameters_in_order_with_units_and_errors(run_dir) -> None:
    out, _ = run_dir
    rep = json.loads((out / "report" / "report.json").read_text())
    p = rep["parameters"]
    assert p["names"] == ["k", "c", "m"] and p["units"] == ["N/m", "N s/m", "kg"]
    targets = rep["targets"]
    t0 = p["targets"][0]
    assert t0["truth"] == pytest.approx(targets["params"][0])  # physical units, parameter order
    nn = t0["methods"]["nearest_neighbour"]
    assert len(nn["params"]) == 3 and 1.0 <= nn["params"][0] <= 1e4  # k in N/m
    theta_true = np.array(targets["theta"][0])
    theta_nn = np.array(next(r for r in json.loads((out / "validate" / "evaluation_rows.json").read_text())
                         if r["optimizer"] == "nearest_neighbour" and r["target_index"] == 0)["theta"])
    assert nn["error"] == pytest.approx(np.abs(theta_nn - theta_true).tolist())
    assert t0["spread_source"] == "npe" and len(t0["spread"]) == 3
    assert "noise_floor" not in t0["methods"]
    assert set(p["error"]) >= {"cma", "nearest_neighbour", "npe", "sil"}


def test_uncertainty_check_is_reported_for_an_ensemble(run_dir) -> None:
    out, _ = run_dir
    unc = json.loads((out / "report" / "report.json").read_text())["uncertainty"]
    assert unc["available"] and 30 <= unc["n_rows"] <= 40  # the test partition of the ok rows
    assert -1.0 <= unc["spearman_rows"] <= 1.0
    assert unc["n_answers"] >= 3


def test_baselines_are_cached_between_runs(run_dir) -> None:
    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out, _ = run_dir
    cache = out / "validate" / "baselines.json"
    before = cache.stat().st_mtime_ns
    run_spec(parse_spec(SPEC), out, stages=["validate"], force=["validate"], progress=False,
             console=Console(file=io.StringIO()))
    assert cache.stat().st_mtime_ns == before  # not refitted, not rewritten


def test_active_learning_rounds_add_simulated_rows_and_keep_the_best_answer(run_dir) -> None:
    out, _ = run_dir
    rounds = json.loads((out / "active" / "rounds.json").read_text())
    assert [r["round"] for r in rounds] == [0, 1, 2]
    added = np.load(out / "active" / "added.npz")
    assert len(added["theta"]) == (4 - rounds[0]["failed"]) + (4 - rounds[1]["failed"])
    assert rounds[1]["train_rows"] == rounds[0]["train_rows"] + 4 - rounds[0]["failed"]
    assert all(r["simulator_runs"] == 4 for r in rounds)  # one proposal per target and round, one batch
    best = [r["best_so_far_mean"] for r in rounds]
    assert best == sorted(best) and best[0] == pytest.approx(rounds[0]["r_actual_mean"])
    assert (out / "active" / "surrogate_round2").is_dir()
    rep = json.loads((out / "report" / "report.json").read_text())
    assert rep["optimizers"]["active_learning"]["r_actual_mean"] == pytest.approx(best[-1])
    assert len(rep["active_learning"]) == 3 and "Active learning rounds" in (out / "report" / "report.md").read_text()


def test_active_learning_with_several_proposals_never_ends_below_its_start(run_dir, tmp_path) -> None:
    import shutil

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out, _ = run_dir
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    spec = parse_spec(SPEC.replace("active: {rounds: 2,", "active: {proposals: 2, keep_start: true, rounds: 1,"))
    summary = run_spec(spec, copy, stages=["active"], progress=False, console=Console(file=io.StringIO()))["active"]
    rounds = summary["rounds"]
    assert [r["simulator_runs"] for r in rounds] == [8, 8]  # 4 targets x 2 proposals, one batch per round
    added = np.load(copy / "active" / "added.npz")
    assert len(added["theta"]) == 8 - rounds[0]["failed"]
    start = {r["target_index"]: r["r_actual"] for r in json.loads((out / "validate" / "validation.json").read_text())
             if r["optimizer"] == "nearest_neighbour"}
    final = json.loads((copy / "active" / "validation.json").read_text())
    assert all(v["r_actual"] >= start[v["target_index"]] - 1e-12 for v in final)
    assert summary["start_r_actual_mean"] == pytest.approx(np.mean([start[k] for k in range(4)]))
    assert rounds[0]["best_so_far_mean"] >= summary["start_r_actual_mean"]
    assert summary["start_simulator_runs_per_target"] >= 1


def test_active_learning_resumes_and_extends_its_rounds(run_dir, tmp_path) -> None:
    import shutil

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out, _ = run_dir
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    shutil.rmtree(copy / "active")

    def active(text: str) -> dict:
        return run_spec(parse_spec(SPEC.replace("active: {rounds: 2,", text)), copy, stages=["active"],
                        progress=False, console=Console(file=io.StringIO()))["active"]

    one = active("active: {rounds: 1,")
    assert one["resumed_after_round"] is None and len(one["rounds"]) == 2
    three = active("active: {rounds: 3,")  # two more rounds: the first two are not simulated again
    assert three["resumed_after_round"] == 1 and len(three["rounds"]) == 4
    assert three["rounds"][:2] == [{**r, "retrain_s": three["rounds"][1].get("retrain_s")} if i == 1 else r
                                   for i, r in enumerate(one["rounds"])]
    assert three["simulator_runs"] == 4 * 4 and (copy / "active" / "surrogate_round3").is_dir()
    best = [r["best_so_far_mean"] for r in three["rounds"]]
    assert best == sorted(best)
    added = np.load(copy / "active" / "added.npz")
    assert len(added["theta"]) == sum(4 - r["failed"] for r in three["rounds"][:3])
    other = active("active: {sigma0: 0.05, rounds: 1,")  # other settings: the saved rounds are not reused
    assert other["resumed_after_round"] is None
