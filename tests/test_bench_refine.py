"""benchmarks/bench_refine.py on the toy bundle: one JSON with both timings, the runs it spent and R before/after."""

from __future__ import annotations

import json
import sys

from benchmark_modules import load
from test_inverter_support import toy_run


def test_bench_refine_writes_one_json(tmp_path_factory, tmp_path, monkeypatch, capsys) -> None:
    run = toy_run(tmp_path_factory.getbasetemp())
    stores = [p.parent for p in (run / "dataset").rglob("_manifest.json")]
    out = tmp_path / "r.json"
    argv = ["--bundle", str(run / "inverter"), "--targets", str(stores[0]), "--limit", "3", "--budget", "8",
            "--starts", "2", "--popsize", "4", "--sim-batch", "4", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_refine.py", *argv])
    assert load("bench_refine").main([*argv, "--dataset-runs", "10"]) == 0
    assert json.loads(out.read_text())["dataset"]["runs"] == 10   # the first 10 of the refine's runs
    assert load("bench_refine").main(argv) == 0
    rec = json.loads(out.read_text())
    assert rec["command"].startswith("python benchmarks/bench_refine.py --bundle")
    assert rec["simulator"] == "toy_oscillator" and rec["simulator_version"] == "1" and rec["device"]
    assert rec["feed"].startswith("default") and rec["refine"]["runs"] == 24 == rec["dataset"]["runs"]
    assert rec["refine_over_dataset"] > 0 and rec["refine"]["never_worse"]
    assert rec["refine"]["r_refined"] >= rec["refine"]["r_best_start"] >= 0
    assert len(rec["per_target"]) == 3
    done = rec["sets"][next(iter(rec["sets"]))]["strategies"]["cma"]["target_done_s"]
    backs = [t["generations_back_s"] for t in rec["per_target"]]
    assert all(len(b) == len(t["batches"]) and b == sorted(b) for b, t in zip(backs, rec["per_target"], strict=True))
    assert 0 < done["median"] <= done["p90"] <= done["max"] == max(b[-1] for b in backs)


def test_bench_refine_shards_a_set_with_first_and_records_the_asks(tmp_path_factory, tmp_path, monkeypatch) -> None:
    """``--first 1 --limit 2`` refines targets 1 and 2 of the set: the same answers as in a run of all three;
    the blocks give the asks' wall, CPU and wait seconds and the extraction thread setting."""
    run = toy_run(tmp_path_factory.getbasetemp())
    store = str(next((run / "dataset").rglob("_manifest.json")).parent)
    bench = load("bench_refine")
    recs = {}
    for name, extra in (("all", ["--limit", "3", "--ask-workers", "0"]),
                        ("shard", ["--first", "1", "--limit", "2", "--extract-workers", "1"])):
        out = tmp_path / f"{name}.json"
        argv = ["--bundle", str(run / "inverter"), "--targets", f"a={store}", "--budget", "8", "--starts", "2",
                "--popsize", "4", "--sim-batch", "4", "--strategy", "corrected", "--skip-dataset", "--bootstrap",
                "50", "--stop", "0", "--out", str(out), *extra]
        monkeypatch.setattr(sys, "argv", ["benchmarks/bench_refine.py", *argv])
        assert bench.main(argv) == 0
        recs[name] = json.loads(out.read_text())
    whole, shard = (recs[n]["sets"]["a"] for n in ("all", "shard"))
    assert shard["first"] == 1 and shard["targets"] == 2 and whole["targets"] == 3
    key = [[(t["r_answer"], t["r_actual"], t["runs"]) for t in s["strategies"]["corrected"]["per_target"]]
           for s in (whole, shard)]
    assert key[1] == key[0][1:]
    b = shard["strategies"]["corrected"]
    assert b["ask_workers"] == 1 and b["ask_wait_s"] >= 0 and 0 < b["ask_cpu_s"] <= b["ask_s"] + 0.05
    assert recs["all"]["sets"]["a"]["strategies"]["corrected"]["ask_workers"] == 0
    assert recs["shard"]["extract_threads"] == 1 and recs["shard"]["first"] == 1


def test_bench_refine_resumes_from_its_log_dir(tmp_path_factory, tmp_path, monkeypatch) -> None:
    """``--log-dir``: a second run of the same command replays every logged run (no simulation) and gives the
    same answers, so a measurement stopped by a time limit is not lost."""
    run = toy_run(tmp_path_factory.getbasetemp())
    store = str(next((run / "dataset").rglob("_manifest.json")).parent)
    bench = load("bench_refine")
    argv = ["--bundle", str(run / "inverter"), "--targets", f"a={store}", "--limit", "2", "--budget", "8",
            "--starts", "2", "--popsize", "4", "--sim-batch", "4", "--strategy", "corrected",
            "--bootstrap", "50", "--log-dir", str(tmp_path / "logs")]
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_refine.py", *argv])
    recs, data = [], []
    for i in range(2):
        out = tmp_path / f"r{i}.json"
        assert bench.main([*argv, "--out", str(out)]) == 0
        recs.append(json.loads(out.read_text())["sets"]["a"]["strategies"]["corrected"]["per_target"])
        data.append(json.loads(out.read_text())["dataset"])
    assert data[0]["runs"] > 0 and data[1].startswith("not timed")   # nothing of the second run's own to time
    assert (tmp_path / "logs" / "refine_a_corrected_0.npz").is_file()
    assert [t["replayed_runs"] for t in recs[0]] == [0, 0]
    assert [t["replayed_runs"] for t in recs[1]] == [t["runs"] for t in recs[1]] and recs[1][0]["runs"] > 0
    assert [t["r_actual"] for t in recs[1]] == [t["r_actual"] for t in recs[0]]


def test_starts_answered_on_one_machine_are_refined_on_another(tmp_path_factory, tmp_path, monkeypatch) -> None:
    """``--answers-out`` answers only (no simulator) and writes each target's starts; ``--answers-in`` refines
    exactly those starts without answering (the GPU machine needs no sbi): the same refine as answering there.
    A file for other targets is refused."""
    import pytest

    run = toy_run(tmp_path_factory.getbasetemp())
    store = str(next((run / "dataset").rglob("_manifest.json")).parent)
    bench = load("bench_refine")
    common = ["--bundle", str(run / "inverter"), "--targets", f"a={store}", "--limit", "3", "--starts", "2",
              "--budget", "8", "--popsize", "4", "--sim-batch", "4", "--strategy", "corrected", "--skip-dataset",
              "--bootstrap", "50", "--stop", "0", "--ask-workers", "0"]
    starts = tmp_path / "starts.json"
    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_refine.py"])
    assert bench.main([*common, "--answers-out", str(starts), "--out", str(tmp_path / "none.json")]) == 0
    assert not (tmp_path / "none.json").exists()  # answering only: nothing refined
    saved = json.loads(starts.read_text())
    assert saved["benchmark"] == "refine_starts" and len(saved["sets"]["a"]["starts"]) == 3
    assert all(len(s) == 2 for s in saved["sets"]["a"]["starts"])
    recs = {}
    for name, extra in (("here", []), ("given", ["--answers-in", str(starts)])):
        out = tmp_path / f"{name}.json"
        assert bench.main([*common, *extra, "--out", str(out)]) == 0
        recs[name] = json.loads(out.read_text())
    key = [[(t["start_r_actual"], t["r_actual"], t["runs"]) for t in
            recs[n]["sets"]["a"]["strategies"]["corrected"]["per_target"]] for n in ("here", "given")]
    assert key[0] == key[1] and recs["given"]["answers_in"] == str(starts)
    assert recs["given"]["method"] == recs["here"]["method"] == saved["method"]   # the starts' method, recorded
    with pytest.raises(SystemExit, match=r"targets 0\+3, not .* 1\+3"):
        bench.main([*common, "--first", "1", "--answers-in", str(starts), "--out", str(tmp_path / "x.json")])
