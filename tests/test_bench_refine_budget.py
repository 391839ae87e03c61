"""benchmarks/bench_refine_budget.py on the toy bundle: every method spends exactly its budget through one
stream, best-so-far never decreases, and the answers are the same twice, with the targets reversed and with
features extracted in worker processes; the JSON holds the equal-budget table."""

from __future__ import annotations

import importlib.util
import itertools
import json
import sys

import numpy as np
import pytest
from benchmark_modules import load
from test_inverter_support import toy_run

bench = load("bench_refine_budget")
sys.modules.setdefault("bench_refine_budget", bench)   # the ask processes find its functions by this name
METHODS = [m for m in bench.METHODS
           if m not in bench._NEEDS or importlib.util.find_spec(bench._NEEDS[m]) is not None]
BUDGET, Q, STARTS = 12, 4, 2


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    import invphys

    run = toy_run(tmp_path_factory.getbasetemp())
    store = next(p.parent for p in (run / "dataset").rglob("_manifest.json"))
    return run / "inverter", store, invphys.load_inverter(run / "inverter")


@pytest.fixture(scope="module", autouse=True)
def cheap_botorch():
    with pytest.MonkeyPatch.context() as mp:
        for name, value in (("restarts", 2), ("raw_samples", 32), ("maxiter", 20), ("mc_samples", 32)):
            mp.setattr(bench.BoTorchQLogEI, name, value)
        yield


def _refine(inv, y, reverse=False, extract_workers=0, ask_procs=2):
    from invphys.inverter.simulate import masked_score

    order = np.arange(len(y))[::-1] if reverse else np.arange(len(y))
    results = inv.invert_many(y[order], top_k=STARTS, seed=0)
    searches = bench.build_searches(inv, [("a", results)], METHODS, BUDGET, Q, 0.1, 0.012, 0)
    sim = inv.simulator()
    stream = bench.refine_all(sim, inv.extractor(sim), searches, masked_score(inv), 5, extract_workers,
                              ask_procs)
    by = {}
    for s in searches:   # keyed by the target's row in y, whatever the order
        by[(int(order[s.key[1]]), s.key[2])] = [(p.tobytes(), v) for p, v in s.history]
    return searches, stream, by


@pytest.fixture(scope="module")
def first(toy, cheap_botorch):
    _bundle, store, inv = toy
    from invphys.core.dataset import DatasetStore

    y = DatasetStore(store).arrays(ok_only=True).y[:3]
    return y, _refine(inv, y)


def test_every_method_spends_exactly_its_budget_and_best_never_decreases(first) -> None:
    _y, (searches, stream, _by) = first
    assert {s.key[2] for s in searches} == set(METHODS) and len(searches) == 3 * len(METHODS)
    fed = np.bincount([k for k, _j in stream.fed], minlength=len(searches))
    assert fed.tolist() == [BUDGET] * len(searches)        # rows that went to the simulator
    for s in searches:
        assert s.runs == BUDGET and len(s.history) == BUDGET
        curve = [s.best_after(b) for b in range(1, BUDGET + 1)]
        assert all(b >= a for a, b in itertools.pairwise(curve)) and 0 <= curve[0] <= curve[-1] <= 1
        # the first runs are the same start candidates for every method
        assert np.array_equal(np.array([p for p, _v in s.history[:STARTS]]), s.starts[:STARTS])
        assert s.best_after(STARTS) == pytest.approx(np.nanmax(np.nan_to_num(s.start_scores)))
        if s.key[2] != "cma":   # search points stay in the box around the best start
            pts = np.array([p for p, _v in s.history[STARTS:]])
            assert np.all(pts >= s.lo - 1e-12) and np.all(pts <= s.hi + 1e-12)
    improved = [s.best_after(BUDGET) > s.best_after(STARTS) for s in searches]
    assert any(improved)


def test_the_same_answers_twice_reversed_and_with_extraction_workers(toy, first) -> None:
    _bundle, _store, inv = toy
    y, (_s, _st, by) = first
    assert _refine(inv, y)[2] == by
    assert _refine(inv, y, reverse=True, ask_procs=0)[2] == by
    assert _refine(inv, y[:2], extract_workers=2)[2] == {k: v for k, v in by.items() if k[0] < 2}


def test_the_json_holds_the_table_and_a_bad_method_is_one_error_line(toy, tmp_path, monkeypatch) -> None:
    bundle, store, _inv = toy
    out = tmp_path / "r.json"
    argv = ["--bundle", str(bundle), "--sets", f"toy={store}", "--limit", "3", "--budgets", "4", "8",
            "--starts", str(STARTS), "--q", str(Q), "--methods", "cma", "optuna_tpe" if "optuna_tpe" in METHODS
            else "cma", "--extract-workers", "0", "--sim-batch", "4", "--bootstrap", "200", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_refine_budget.py", *argv])
    assert bench.main(argv) == 0
    rec = json.loads(out.read_text())
    assert rec["command"].startswith("python benchmarks/bench_refine_budget.py --bundle") and rec["complete"]
    assert rec["simulator"] == "toy_oscillator" and rec["device"] and rec["runs"] == 3 * 8 * len(set(argv[15:17]))
    cell = rec["table"]["toy"]["cma"]["budgets"]["8"]
    assert len(cell["per_target"]) == 3 and cell["ci95"][0] <= cell["mean"] <= cell["ci95"][1]
    if "optuna_tpe" in METHODS:
        d = rec["table"]["toy"]["optuna_tpe"]["budgets"]["8"]["vs_cma"]
        tpe = rec["table"]["toy"]["optuna_tpe"]["budgets"]["8"]["per_target"]
        assert d["mean"] == pytest.approx(np.mean(np.array(tpe) - cell["per_target"]))
    with pytest.raises(SystemExit, match="unknown method 'nelder'"):
        bench.main([*argv[:-2], "--methods", "nelder"])


def test_cma_is_the_sim_refine_search(toy, first) -> None:
    """With the whole cube as the box, ``cma`` finds what ``refine`` (``invert --sim-refine``) finds."""
    from invphys.inverter.refine import refine
    from invphys.inverter.simulate import masked_score

    _bundle, _store, inv = toy
    y = first[0]
    ours = bench.build_searches(inv, [("a", inv.invert_many(y, top_k=STARTS, seed=0))], ["cma"], BUDGET, Q, 1.0,
                                0.012, 0)
    sim = inv.simulator()
    bench.refine_all(sim, inv.extractor(sim), ours, masked_score(inv), 5)
    results = inv.invert_many(y, top_k=STARTS, seed=0)
    recs = refine(inv, results, BUDGET, popsize=Q, sigma0=0.012, batch_size=5, seed=0, simulator=sim,
                  strategy="cma")
    assert [r["runs"] for r in recs] == [s.runs for s in ours] == [BUDGET] * len(y)
    assert [r["r_actual"] for r in recs] == [s.best_after(BUDGET) for s in ours]
    assert [r.candidates[0].theta.tobytes() for r in results] == [s.t.theta.tobytes() for s in ours]


def test_corrected_is_the_default_sim_refine_search(toy, first) -> None:
    """With the whole cube as the box and no stored-row starts, ``corrected`` finds what the default
    ``refine`` (``invert --sim-refine``, strategy corrected) finds."""
    from invphys.inverter.refine import refine
    from invphys.inverter.simulate import masked_score

    _bundle, _store, inv = toy
    y = first[0]
    ours = bench.build_searches(inv, [("a", inv.invert_many(y, top_k=STARTS, seed=0))], ["corrected"], BUDGET, Q,
                                1.0, 0.012, 0)
    sim = inv.simulator()
    bench.refine_all(sim, inv.extractor(sim), ours, masked_score(inv), 5)
    results = inv.invert_many(y, top_k=STARTS, seed=0)
    recs = refine(inv, results, BUDGET, popsize=Q, sigma0=0.012, batch_size=5, seed=0, simulator=sim,
                  strategy="corrected", known_starts=0, stop=0.0)
    assert [r["runs"] for r in recs] == [s.runs for s in ours] == [BUDGET] * len(y)
    assert [r["r_actual"] for r in recs] == [s.best_after(BUDGET) for s in ours]


def test_shards_merge_into_the_unsharded_table(toy, tmp_path, monkeypatch) -> None:
    """``--first``/``--limit`` shards joined by ``--merge`` give the table of one run over all targets."""
    bundle, store, _inv = toy
    base = ["--bundle", str(bundle), "--sets", f"toy={store}", "--budgets", "4", "8", "--starts", str(STARTS),
            "--q", str(Q), "--methods", "cma", "corrected", "--extract-workers", "0", "--sim-batch", "4",
            "--bootstrap", "200"]
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_refine_budget.py"])
    outs = {}
    for name, first_, limit in (("all", 0, 3), ("a", 0, 2), ("b", 2, 1)):
        outs[name] = tmp_path / f"{name}.json"
        assert bench.main([*base, "--first", str(first_), "--limit", str(limit), "--out", str(outs[name])]) == 0
    merged = tmp_path / "m.json"
    assert bench.main(["--merge", str(outs["b"]), str(outs["a"]), "--bootstrap", "200", "--out", str(merged)]) == 0
    whole, joined = (json.loads(p.read_text()) for p in (outs["all"], merged))
    for method in ("cma", "corrected"):
        w, j = whole["table"]["toy"][method], joined["table"]["toy"][method]
        assert j["targets"] == 3 and j["runs"] == w["runs"]
        for b in ("4", "8"):
            assert j["budgets"][b]["per_target"] == w["budgets"][b]["per_target"]
            assert j["budgets"][b]["mean"] == pytest.approx(w["budgets"][b]["mean"])
    assert joined["table"]["toy"]["corrected"]["budgets"]["8"]["vs_cma"]["mean"] == pytest.approx(
        whole["table"]["toy"]["corrected"]["budgets"]["8"]["vs_cma"]["mean"])
    other = json.loads(outs["a"].read_text())
    other["q"] = 99
    outs["a"].write_text(json.dumps(other))
    with pytest.raises(SystemExit, match="differ in q"):
        bench.main(["--merge", str(outs["a"]), str(outs["b"]), "--out", str(merged)])
