"""``examples/anisompm/benchmarks/bench_fused.py`` on the CPU: the script runs end to end at the tiny preset and
writes its result (the fused path equal to the plain one there), and its passes keep to the wall budget."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[3]
SCRIPT = ROOT / "examples" / "anisompm" / "benchmarks" / "bench_fused.py"


def test_bench_fused_runs_on_the_cpu_and_writes_its_result(tmp_path):
    pytest.importorskip("taichi")
    out = tmp_path / "fused.json"
    proc = subprocess.run([sys.executable, str(SCRIPT), "--preset", "tiny", "--arch", "cpu", "--runs", "2",
                           "--batch", "2", "--frames", "2", "--parity-steps", "4", "--ways", "fused", "fused_stored",
                           "--out", str(out)],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.exists(), proc.stderr[-3000:]
    rec = json.loads(out.read_text())
    assert rec["script"] == "examples/anisompm/benchmarks/bench_fused.py"
    assert rec["command"].startswith("python ") and rec["device"] and rec["simulator_version"]
    assert rec["errors"] == {}
    ways = ("plain", "fused", "fused_stored")
    assert list(rec["passes"]) == [*ways, *(f"{w}_again" for w in ways)]
    assert all(p["seconds_per_run"] > 0 and p["failed"] == 0 for p in rec["passes"].values())
    assert set(rec["kernel_seconds_per_launch"]["fused"]) == {"fused", "fgrid", "substep_total"}
    # the CPU's serialised scatter: the same sums in the same order, rounded differently (fast math)
    parity, scale = rec["state_parity"], rec["state_parity"]["scale"]
    assert parity["plain_vs_plain_again"] == {"x": 0.0, "d": 0.0}
    for way in ways[1:]:
        assert all(parity[f"{way}_vs_plain"][k] <= 1e-4 * scale[k] for k in scale)
        assert rec["feature_agreement"][f"{way}_vs_plain"]["median_rel_diff_all"] <= 1e-3
    assert set(rec["runs_speedup_vs_plain"]) == {"fused", "fused_stored"}
    assert "partial" not in rec      # the last write is the whole result


class _SlowSim:
    """A simulator stand-in whose whole pass takes ``seconds``."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.calls: list[int] = []

    def simulate(self, params):
        self.calls.append(len(params))
        if len(params) > 2:
            time.sleep(self.seconds)
        return [SimpleNamespace(ok=False)] * len(params)


def test_passes_stop_when_the_next_would_overrun_the_budget():
    spec = importlib.util.spec_from_file_location("bench_fused_probe", SCRIPT)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    sims = {"plain": _SlowSim(0.3), "fused": _SlowSim(0.3)}   # plain first, as _build orders them
    out: dict = {"passes": {}}
    ex = SimpleNamespace(feature_names=["a"])
    feats = bench._run_passes(sims, np.zeros((4, 9)), ex, SimpleNamespace(budget_s=0.5, out=None), time.perf_counter(), out)
    assert list(feats) == ["plain"]                 # 0.3 s spent: no other 0.3 s pass fits in the 0.5 s
    assert "seconds_per_run" in out["passes"]["plain"]
    assert all("skipped" in out["passes"][n] for n in ("fused", "plain_again", "fused_again"))
    assert sims["fused"].calls == []                # not even warmed
