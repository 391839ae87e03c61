"""benchmarks/bench_corrected_surrogate.py on the toy bundle: the correction grid, the exact-rule check on stored
rows and the short-distance probe on the (deterministic) toy simulator."""

from __future__ import annotations

import json

import numpy as np
import pytest
from benchmark_modules import load
from test_inverter_support import toy_run

bench = load("bench_corrected_surrogate")


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    run = toy_run(tmp_path_factory.getbasetemp())
    return run / "inverter", next(p.parent for p in (run / "dataset").rglob("_manifest.json"))


def test_the_correction_grid_and_the_exact_rule(toy, tmp_path) -> None:
    bundle, store = toy
    out = tmp_path / "c.json"
    assert bench.main(["--bundle", str(bundle), "--sets", "test=@test", f"rows={store}", "--k", "4", "--bandwidth",
                       "0.1", "--prior", "0", "1", "--rule-sets", f"rows={store}", "--margins", "0", "0.9",
                       "--splits", "2", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert set(data["sets"]["test"]["variants"]) == {"plain", "raw k=4 h=0.1 prior=0.0", "raw k=4 h=0.1 prior=1.0",
                                                     "log k=4 h=0.1 prior=0.0", "log k=4 h=0.1 prior=1.0"}
    rule = data["exact_rule"]["rows"]
    # the targets are stored rows themselves: the exact lookup finds each one in its half or a near twin
    assert rule["oracle_max"] >= max(rule["surrogate_pick_A"], rule["exact_lookup_B"]) - 1e-12
    assert rule["hybrid_margin_0.9"] == pytest.approx(rule["exact_lookup_B"])  # margin ~1: always the stored row


def test_the_probe_reruns_a_row_exactly_at_distance_zero(toy, tmp_path) -> None:
    bundle, _ = toy
    out = tmp_path / "p.json"
    assert bench.main(["--bundle", str(bundle), "--probe", "3", "--probe-dirs", "2", "--probe-distances", "0", "0.2",
                       "--sim-batch", "8", "--out", str(out)]) == 0
    probe = json.loads(out.read_text())["probe"]
    assert probe["runs"] == 3 * 2 * 2
    zero, far = probe["by_distance"]["0"], probe["by_distance"]["0.2"]
    assert zero["r_new_run_vs_row"] == pytest.approx(1.0)   # the toy simulator is deterministic
    assert zero["r_surrogate_anchored"] == pytest.approx(1.0)  # the row's residual restores its features
    assert far["r_new_run_vs_row"] < 1.0 and np.isfinite(far["residual_corr"])
