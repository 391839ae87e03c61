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
    text = (out / "report" / "report.json").read_text()
    assert "\n" not in text  # compact: one line (committed reports stay small)
    rep = json.loads(text)
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
        assert sil["simulator_runs"] == 9 and sil["simulator_time_s"] > 0
        assert sil["r_actual"] >= nn["r_actual"] - 1e-12  # its start was simulated too
    ev = {(r["optimizer"], r["target_index"]): r for r in json.loads((out / "validate" / "evaluation_rows.json").read_text())}
    # the loop's own score is the validated R_actual (no reality gap by construction)
    assert all(abs(ev[("sil", k)]["in_loop_score"] - by[("sil", k)]["r_actual"]) < 1e-9 for k in range(8))
    # the report's cost column counts the simulator's own time per target (a replayed memo too)
    proto = json.loads((out / "report" / "report.json").read_text())["optimizers"]
    assert proto["sil"]["simulator_time_s"] == pytest.approx(info["simulator_time_s"] / 8)


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


def test_active_rounds_resume_when_only_the_batching_changes(run_dir, tmp_path) -> None:
    """The rounds' checkpoint keys the simulator and features by their identity, the validator without its
    batch size: a call on another machine with other batching (as a GPU call with continuous slots)
    resumes instead of starting over; a changed validator setting that matters does not."""
    import shutil

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out, _ = run_dir
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    shutil.rmtree(copy / "active")

    def active(text: str, validator: str = "validator: {type: simulator, batch_size: 64}") -> dict:
        spec = SPEC.replace("active: {rounds: 2,", text).replace("validator: {type: simulator, batch_size: 64}",
                                                                   validator)
        return run_spec(parse_spec(spec), copy, stages=["active"], progress=False,
                        console=Console(file=io.StringIO()))["active"]

    assert active("active: {rounds: 1,")["resumed_after_round"] is None
    two = active("active: {rounds: 2,", "validator: {type: simulator, batch_size: 3}")
    assert two["resumed_after_round"] == 1 and len(two["rounds"]) == 3
    other = active("active: {rounds: 2,", "validator: {type: simulator, batch_size: 3, overrides: {sleep_s: 0.0}}")
    assert other["resumed_after_round"] is None


class _QuadSim:
    """A deterministic stand-in for the simulator evaluator: features = theta (counts runs and calls)."""

    def __init__(self) -> None:
        self.runs, self.calls, self.wall_time_s, self.device = 0, 0, 0.0, "toy"

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        self.runs += len(theta)
        self.calls += 1
        self.wall_time_s += 0.01 * len(theta)
        return np.array(theta, dtype=np.float64)


def test_polish_never_worse_respects_budget_and_replays_its_log(tmp_path) -> None:
    from invphys.core.objectives import recovery_reward
    from invphys.evaluators.polish import BatchLog, polish

    rng = np.random.default_rng(0)
    targets = rng.uniform(0.2, 0.8, (6, 3))
    starts = np.clip(targets + rng.normal(0, 0.15, targets.shape), 0, 1)
    starts[5] = targets[5] + 1e-4  # already near-perfect: above `below`, left alone
    scales = np.ones(3)
    r0 = recovery_reward(starts, targets, scales)

    def run(budget: int) -> tuple:
        sim = _QuadSim()
        log = BatchLog(tmp_path / "polish.npz", "k", sim, chunk=7)  # logged in chunks of 7 runs
        return polish(targets, starts, r0, starts.copy(), scales, log, budget, popsize=4, sigma0=0.1,
                      below=0.99, seed=1), sim, log

    pol, sim, _ = run(4)  # one generation per polished target
    assert pol.polished.tolist() == [True] * 5 + [False]
    assert pol.runs.tolist() == [4] * 5 + [0] and sim.runs == 20 and sim.calls == 3  # 20 = 7+7+6, no start re-run
    assert np.all(pol.r_actual >= r0) and pol.r_actual[5] == r0[5] and np.array_equal(pol.theta[5], starts[5])
    assert np.allclose(recovery_reward(pol.features, targets, scales), pol.r_actual)
    more, sim2, log2 = run(12)  # three generations: the logged first one is replayed, not simulated again
    assert more.runs.tolist() == [12] * 5 + [0] and sim2.runs == 40 and log2.replayed_runs == 20
    assert np.all(more.r_actual >= pol.r_actual) and more.r_actual[:5].mean() > r0[:5].mean()
    again, sim3, _ = run(12)  # a finished polish costs nothing again and gives the same answers
    assert sim3.runs == 0 and np.array_equal(again.theta, more.theta) and again.seconds == pytest.approx(more.seconds)


def test_active_polish_is_off_by_default_and_counts_its_runs(run_dir, tmp_path) -> None:
    import shutil

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out, _ = run_dir
    assert "polish" not in parse_spec(SPEC).section_dump(["active"])["active"]  # default: stage keys unchanged
    assert not (out / "active" / "polish.json").exists()
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    spec = parse_spec(SPEC.replace("active: {rounds: 2,",
                                   "active: {polish: {budget: 8, popsize: 4, sigma0: 0.1, below: 0.999}, rounds: 2,"))
    s = run_spec(spec, copy, stages=["active", "report"], progress=False, console=Console(file=io.StringIO()))
    summary = s["active"]
    assert summary["resumed_after_round"] == 2  # the polish does not invalidate the finished rounds
    pol = summary["polish"]
    val = json.loads((copy / "active" / "validation.json").read_text())
    before = {v["target_index"]: v for v in val if v["optimizer"] == "active_learning"}
    after = {v["target_index"]: v for v in val if v["optimizer"] == "active_polished"}
    assert sorted(after) == sorted(before) == [0, 1, 2, 3]
    polished = [k for k in before if before[k]["r_actual"] < 0.999]
    assert pol["polished"] == len(polished) and pol["simulator_runs"] == 8 * len(polished) and pol["worse"] == 0
    for k in before:
        assert after[k]["r_actual"] >= before[k]["r_actual"]
        extra = 8 if k in polished else 0
        assert after[k]["simulator_runs"] == pytest.approx(before[k]["simulator_runs"] + extra)
    rep = json.loads((copy / "report" / "report.json").read_text())
    assert rep["optimizers"]["active_polished"]["r_actual_mean"] == pytest.approx(pol["r_actual_after_mean"])
    assert rep["optimizers"]["active_learning"]["r_actual_mean"] == pytest.approx(pol["r_actual_before_mean"])
    (copy / "active" / "DONE.json").unlink()  # force a re-run: the logged batches are replayed
    again = run_spec(spec, copy, stages=["active"], progress=False, console=Console(file=io.StringIO()))["active"]
    assert again["polish"]["replayed_runs"] == pol["simulator_runs"]
    assert again["polish"]["r_actual_after_mean"] == pytest.approx(pol["r_actual_after_mean"])


def test_active_polish_passes_start_from_the_previous_pass_and_replay_it(run_dir, tmp_path) -> None:
    import shutil

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out, _ = run_dir
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    first = "{budget: 4, popsize: 4, sigma0: 0.1, below: 0.999}"
    one = parse_spec(SPEC.replace("active: {rounds: 2,", f"active: {{polish: {first}, rounds: 2,"))
    quiet = {"progress": False, "console": Console(file=io.StringIO())}
    single = run_spec(one, copy, stages=["active"], **quiet)["active"]["polish"]
    (copy / "active" / "DONE.json").unlink()
    two = parse_spec(SPEC.replace("active: {rounds: 2,", f"active: {{polish: [{first}, {{budget: 4, popsize: 4, "
                                  "sigma0: 0.05, below: 0.9995}], rounds: 2,"))
    pol = run_spec(two, copy, stages=["active"], **quiet)["active"]["polish"]
    assert len(pol["passes"]) == 2 and len(pol["settings"]) == 2
    p1, p2 = pol["passes"]
    assert p1["replayed_runs"] == single["simulator_runs"] and p1["r_actual_after_mean"] == single["r_actual_after_mean"]
    assert p2["r_actual_before_mean"] == pytest.approx(p1["r_actual_after_mean"])  # pass 2 starts from pass 1
    assert pol["r_actual_after_mean"] == pytest.approx(p2["r_actual_after_mean"])
    assert p2["r_actual_after_mean"] >= p1["r_actual_after_mean"]
    assert pol["simulator_runs"] == p1["simulator_runs"] + p2["simulator_runs"] > p1["simulator_runs"]
    assert (copy / "active" / "polish_pass2.npz").is_file()
    val = json.loads((copy / "active" / "validation.json").read_text())
    before = {v["target_index"]: v for v in val if v["optimizer"] == "active_learning"}
    after = {v["target_index"]: v for v in val if v["optimizer"] == "active_polished"}
    extra = sum(after[k]["simulator_runs"] - before[k]["simulator_runs"] for k in before)
    assert extra == pytest.approx(pol["simulator_runs"])  # every pass's runs are counted per target
    (copy / "active" / "DONE.json").unlink()  # both passes replay their logs: nothing is simulated again
    again = run_spec(two, copy, stages=["active"], **quiet)["active"]["polish"]
    assert again["replayed_runs"] == pol["simulator_runs"]
    assert again["r_actual_after_mean"] == pytest.approx(pol["r_actual_after_mean"])


def test_active_polish_rejects_an_empty_list_of_passes() -> None:
    from invphys.core.spec import parse_spec

    with pytest.raises(Exception, match="1 to 8 passes"):
        parse_spec(SPEC.replace("active: {rounds: 2,", "active: {polish: [], rounds: 2,"))


def test_active_polish_confirm_is_key_neutral_off_and_counts_and_replays_its_runs(run_dir, tmp_path) -> None:
    import shutil

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    plain = "{budget: 4, popsize: 4, sigma0: 0.1, below: 0.999}"
    off = parse_spec(SPEC.replace("active: {rounds: 2,", "active: {polish: {budget: 4, popsize: 4, sigma0: 0.1, "
                                  "below: 0.999, confirm: 0, confirm_candidates: 3}, rounds: 2,"))
    assert off.section_dump(["active"]) == parse_spec(SPEC.replace(
        "active: {rounds: 2,", f"active: {{polish: {plain}, rounds: 2,")).section_dump(["active"])  # key unchanged
    assert off.active.polish.key_dump() == {"budget": 4, "popsize": 4, "sigma0": 0.1, "below": 0.999}
    with pytest.raises(Exception, match="confirm"):
        parse_spec(SPEC.replace("active: {rounds: 2,", "active: {polish: {confirm: -1}, rounds: 2,"))
    with pytest.raises(Exception, match="confirm_candidates"):
        parse_spec(SPEC.replace("active: {rounds: 2,", "active: {polish: {confirm: 2, confirm_candidates: 0}, rounds: 2,"))
    out, _ = run_dir
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    quiet = {"progress": False, "console": Console(file=io.StringIO())}
    first = run_spec(off, copy, stages=["active"], **quiet)["active"]["polish"]  # confirm off: a plain polish
    assert "confirm" not in first and first["settings"] == {"budget": 4, "popsize": 4, "sigma0": 0.1, "below": 0.999}
    (copy / "active" / "DONE.json").unlink()
    on = parse_spec(SPEC.replace("active: {rounds: 2,", "active: {polish: {budget: 4, popsize: 4, sigma0: 0.1, "
                                 "below: 0.999, confirm: 2, confirm_candidates: 3}, rounds: 2,"))
    pol = run_spec(on, copy, stages=["active", "report"], **quiet)["active"]["polish"]
    c = pol["confirm"]
    n_pol, n = pol["polished"], pol["targets"]
    assert pol["replayed_runs"] == first["simulator_runs"] == 4 * n_pol  # the log made without confirm replays
    sizes = [t["candidates"] for t in c["targets"]]
    assert sorted(sizes) == [1] * (n - n_pol) + [3] * n_pol and c["simulator_runs"] == 2 * sum(sizes)
    assert pol["simulator_runs"] == first["simulator_runs"] + c["simulator_runs"]
    # the toy simulator is deterministic: every re-run reproduces, so the answers and their R stay
    assert c["changed"] == 0 and c["r_confirmed_mean"] == pytest.approx(c["r_selected_mean"], abs=1e-12)
    assert c["r_selected_mean"] == pytest.approx(first["r_actual_after_mean"], abs=1e-12)
    val = json.loads((copy / "active" / "validation.json").read_text())
    before = {v["target_index"]: v for v in val if v["optimizer"] == "active_learning"}
    after = {v["target_index"]: v for v in val if v["optimizer"] == "active_polished"}
    for t, k in zip(c["targets"], sorted(after), strict=True):  # the rows carry the confirmed R and its runs
        assert after[k]["r_actual"] == pytest.approx(t["r_confirmed"], abs=1e-12)
        assert after[k]["simulator_runs"] == pytest.approx(before[k]["simulator_runs"] + t["runs"] +
                                                           (4 if t["candidates"] == 3 else 0))
    (copy / "active" / "DONE.json").unlink()  # a re-run replays the search and the confirmation
    again = run_spec(on, copy, stages=["active"], **quiet)["active"]["polish"]
    assert again["replayed_runs"] == pol["simulator_runs"] and again["confirm"] == {**c, "replayed_runs":
                                                                                  c["simulator_runs"]}


def test_active_polish_with_other_settings_starts_its_own_log_afresh(run_dir, tmp_path) -> None:
    """The stage's polish log lives in invphys's own folder: other settings replace it (a user's log is
    refused instead, tests/test_inverter_polish.py)."""
    import shutil

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out, _ = run_dir
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    base = "active: {polish: {budget: 4, popsize: 4, sigma0: SIGMA, below: 0.999}, rounds: 2,"
    for sigma in ("0.1", "0.2"):
        spec = parse_spec(SPEC.replace("active: {rounds: 2,", base.replace("SIGMA", sigma)))
        summary = run_spec(spec, copy, stages=["active"], progress=False, console=Console(file=io.StringIO()))
        assert summary["active"]["polish"]["replayed_runs"] == 0  # the second settings' batches are new
    assert (copy / "active" / "polish.npz").is_file()
