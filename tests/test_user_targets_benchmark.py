"""benchmarks/bench_user_targets.py: user-like sets scored next to a lookup over all data and the truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from benchmark_modules import load

QUICK_BUNDLE = "inverters/orange_peel_quick"
QUICK_STORE = "datasets/orange_peel_quick"


def test_scores_each_method_against_a_lookup_over_all_stores(tmp_path: Path) -> None:
    bench = load("bench_user_targets")
    out = tmp_path / "user_targets.json"
    assert bench.main(["--bundle", QUICK_BUNDLE, "--targets", f"quick={QUICK_STORE}", "--all-data", QUICK_STORE,
                       "--methods", "gc_ppo_vae", "--limit", "6", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["validated"] is False and report["command"] and report["device"]
    rows = report["sets"]["quick"]["methods"]
    assert set(rows) == {"gc_ppo_vae", "nearest_neighbour_all", "truth"}
    assert all(r["n"] == 6 for r in rows.values())
    # the targets are rows of the lookup's store: the lookup finds each one itself, so it scores as the truth
    assert np.isclose(rows["nearest_neighbour_all"]["r_mean"], rows["truth"]["r_mean"])
    diff = rows["gc_ppo_vae"]["vs_nearest_neighbour_all"]
    assert np.isclose(diff["mean_diff"], rows["gc_ppo_vae"]["r_mean"] - rows["nearest_neighbour_all"]["r_mean"])
    lo, hi = rows["gc_ppo_vae"]["r_ci95"]
    assert lo <= rows["gc_ppo_vae"]["r_mean"] <= hi
