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
    assert load("bench_refine").main(argv) == 0
    rec = json.loads(out.read_text())
    assert rec["command"].startswith("python benchmarks/bench_refine.py --bundle")
    assert rec["simulator"] == "toy_oscillator" and rec["simulator_version"] == "1" and rec["device"]
    assert rec["feed"].startswith("default") and rec["refine"]["runs"] == 24 == rec["dataset"]["runs"]
    assert rec["refine_over_dataset"] > 0 and rec["refine"]["never_worse"]
    assert rec["refine"]["r_refined"] >= rec["refine"]["r_best_start"] >= 0
    assert len(rec["per_target"]) == 3
