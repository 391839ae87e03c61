"""benchmarks/bench_refine.py with several strategies and target sets on the toy: same targets and starts,
per-strategy means with intervals, paired differences, the JSON written after every strategy."""

from __future__ import annotations

import json
import sys

import pytest
from benchmark_modules import load
from test_inverter_support import toy_run


def test_bench_refine_compares_strategies_on_two_target_sets(tmp_path_factory, tmp_path, monkeypatch) -> None:
    run = toy_run(tmp_path_factory.getbasetemp())
    store = str(next((run / "dataset").rglob("_manifest.json")).parent)
    out = tmp_path / "r.json"
    argv = ["--bundle", str(run / "inverter"), "--targets", f"a={store}", f"b={store}", "--limit", "4",
            "--budget", "12", "--starts", "2", "--popsize", "4", "--sim-batch", "4", "--strategy", "cma", "corrected",
            "--bootstrap", "200", "--skip-dataset", "--stop", "0", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_refine.py", *argv])
    bench = load("bench_refine")
    writes = []
    real_write = bench._write
    monkeypatch.setattr(bench, "_write", lambda result, o: (writes.append(json.dumps(result)), real_write(result, o)))
    assert bench.main(argv) == 0
    rec = json.loads(out.read_text())
    assert len(writes) == 5   # after every strategy of every set, and the first refine before its dataset timing
    assert rec["refine"]["strategy"] == "cma" and rec["refine"]["runs"] == 48 and rec["dataset"] is None
    for name in ("a", "b"):
        s = rec["sets"][name]
        cma, cor = s["strategies"]["cma"], s["strategies"]["corrected"]
        assert s["targets"] == 4 and cma["runs"] == cor["runs"] == 48
        for b in (cma, cor):   # runs, time and R at intermediate budgets per target; the proposals' time
            assert b["runs_per_target"] == 12 and b["stopped"] == 0 and b["ask_s"] > 0
            assert b["simulator_s_per_target"] == pytest.approx(b["simulator_s"] / 4)
            assert list(b["r_at_runs"]) == ["12"] and b["r_at_runs"]["12"] == pytest.approx(b["r_refined"])
        assert [t["r_answer"] for t in cma["per_target"]] == [t["r_answer"] for t in cor["per_target"]]  # same starts
        assert cor["per_target"][0]["known_starts"] == 8 and cma["per_target"][0]["known_starts"] == 0
        ci = cor["r_refined_ci"]
        assert ci["lo"] <= ci["mean"] <= ci["hi"] and cor["never_worse"] and cma["never_worse"]
        diff = [c["r_actual"] - m["r_actual"] for c, m in zip(cor["per_target"], cma["per_target"], strict=True)]
        assert abs(s["paired"]["corrected - cma"]["mean"] - sum(diff) / 4) < 1e-12
    same = [[t["r_actual"] for t in rec["sets"][n]["strategies"]["corrected"]["per_target"]] for n in ("a", "b")]
    assert same[0] == same[1]   # the same targets again: the same answers
    stopped = tmp_path / "stop.json"   # the default stop: the toy's stored rows are exact, its targets stop early
    argv = [*argv[:argv.index("--stop")], "--out", str(stopped)]
    assert bench.main(argv) == 0
    cor = json.loads(stopped.read_text())["sets"]["a"]["strategies"]["corrected"]
    assert cor["stopped"] > 0 and cor["runs_per_target"] < 12
    assert cor["runs"] == sum(t["runs"] for t in cor["per_target"]) and all(t["r_actual"] >= 0.98 for t in
                                                                            cor["per_target"] if t["stopped"])


def test_r_at_runs_reads_each_targets_best_so_far() -> None:
    bench = load("bench_refine")
    recs = [{"best_r_by_run": [0.5 + 0.01 * i for i in range(40)], "r_actual": 0.89},
            {"best_r_by_run": [0.9] * 20, "r_actual": 0.9},          # stopped after 20 runs
            {"best_r_by_run": [None] * 40, "r_actual": None}]        # every run failed: 0
    got = bench.r_at_runs(recs, 40)
    assert list(got) == ["16", "32", "40"]
    assert got["16"] == pytest.approx((0.65 + 0.9) / 3) and got["40"] == pytest.approx((0.89 + 0.9) / 3)
