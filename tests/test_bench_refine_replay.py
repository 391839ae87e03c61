"""benchmarks/bench_refine_replay.py on a small synthetic bench_refine result: hand-computed answers."""

from __future__ import annotations

import json

import pytest
from benchmark_modules import load

replay = load("bench_refine_replay")


def _doc() -> dict:
    a = {"runs": 10, "batches": [2, 4, 4], "best_r_free": 0.4, "r_actual": 0.6, "stopped": False,
         "best_r_by_run": [0.5, 0.6] + [0.6] * 8}
    b = {"runs": 10, "r_actual": 0.7, "stopped": False,   # no batches, no best_r_free: assumed, -inf
         "best_r_by_run": [0.5] * 4 + [0.7] * 6}
    c = {"runs": 6, "batches": [2, 4], "best_r_free": None, "r_actual": 0.9, "stopped": True,
         "best_r_by_run": [0.5, 0.5, 0.9, 0.9, 0.9, 0.9]}
    return {"script": "benchmarks/bench_refine.py", "device": "a GPU", "strategy": "corrected",
            "sets": {"u": {"strategies": {"corrected": {"wall_s": 10.0, "runs": 20, "per_target": [a, b]}}},
                     "e": {"strategies": {"corrected": {"wall_s": 3.0, "runs": 6, "per_target": [c]}}}}}


def _rule(sets: dict, name: str, stop, patience: int, gain) -> dict:
    return next(r for r in sets[name]["rules"] if (r["stop"], r["patience"], r["min_gain"]) == (stop, patience, gain))


def test_the_replay_gives_the_hand_computed_answers() -> None:
    sets = replay.run(_doc(), [None, 0.65], [4], [0.05], popsize=4)
    u = sets["u"]
    assert u["targets"] == 2 and u["s_per_run"] == 0.5 and u["batches"].startswith("assumed for 1 of 2")
    # a: decisions at 2 (< patience) and 6: best(6) - best(2) = 0.6 - 0.6 < 0.05, stalled at 6 runs
    # b: generations 4, 4, 2: at 4, best(0) = -inf (gain inf); at 8, 0.7 - 0.5 = 0.2: runs all 10
    row = _rule(sets, "u", None, 4, 0.05)
    assert row["runs_per_target"] == 8.0 and row["r"]["mean"] == pytest.approx(0.65) and row["r_min"] == 0.6
    assert (row["stalled"], row["stopped"], row["cut_short"]) == (1, 0, 0) and row["gpu_s_per_target"] == 4.0
    assert 0.6 <= row["r"]["lo"] <= row["r"]["hi"] <= 0.7 and row["r_minus_measured"]["mean"] == pytest.approx(0.0)
    # stop 0.65: a never reaches it (10 runs), b reaches it at its decision after 8 runs
    row = _rule(sets, "u", 0.65, 0, None)
    assert row["runs_per_target"] == 9.0 and row["stopped"] == 1 and row["gpu_s_per_target"] == 4.5
    # stop 0.65 and the stall rule: a stalls at 6, b stops at 8
    row = _rule(sets, "u", 0.65, 4, 0.05)
    assert row["runs_per_target"] == 7.0 and (row["stalled"], row["stopped"]) == (1, 1)
    # c was stopped at 6 runs by the measured rule: without a stop the replay cannot go on (cut short)
    e = sets["e"]
    assert e["batches"] == "recorded" and e["s_per_run"] == 0.5
    row = _rule(sets, "e", None, 0, None)
    assert (row["runs_per_target"], row["cut_short"], row["r"]["mean"]) == (6.0, 1, 0.9)
    # ... but the stall rule decides there: best(6) - best(2) = 0.4, no stall; at 2 runs (< patience 4) none
    assert _rule(replay.run(_doc(), [0.65], [4], [0.5]), "e", 0.65, 4, 0.5)["stopped"] == 1


def test_main_writes_the_result_with_its_note(tmp_path, capsys) -> None:
    src = tmp_path / "refine.json"
    src.write_text(json.dumps(_doc()))
    out = tmp_path / "replay.json"
    assert replay.main([str(src), "--stop", "0", "--patience", "4", "--min-gain", "0.05", "--popsize", "4",
                        "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["script"] == "benchmarks/bench_refine_replay.py" and "--patience 4" in res["command"]
    assert "a GPU" in res["device"] and "projected" in res["note"] and "prefix" in res["note"]
    assert _rule(res["sets"], "u", None, 4, 0.05)["runs_per_target"] == 8.0
    assert "assumed for 1 of 2" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="holds no per-target records"):
        src.write_text(json.dumps({"sets": {}}))
        replay.main([str(src)])
