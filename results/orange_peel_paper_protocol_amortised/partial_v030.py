"""Summarise a validate stage that was stopped before the end (simulator 0.3.0, this folder's README).

Reads OUT/invert/targets.json, OUT/validate/evaluation_rows.json and OUT/validate/simulated.jsonl; scores every
answer that was simulated (R_actual, the paper's reward against the target's stored features with the
training scales), and the lookup (nearest_neighbour) on every target from its training row's stored
features (a stored simulation of that very vector; re-run noise median R_gt 0.9998,
benchmarks/results/simulator_noise_paper.json). Paired differences against the lookup on the targets where
the method's answer was simulated. Usage: python partial_v030.py runs/protocol_paper_amortised OUT.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from invphys.core.dataset import DatasetStore
from invphys.core.objectives import recovery_reward
from invphys.evaluation.stats import mean_with_ci, paired_difference


def main(run: Path, out: Path) -> dict:
    targets = json.loads((run / "invert" / "targets.json").read_text())
    rows = json.loads((run / "validate" / "evaluation_rows.json").read_text())
    sims = [json.loads(line) for line in (run / "validate" / "simulated.jsonl").read_text().splitlines()]
    memo = {tuple(np.round(s["theta"], 10)): s["features"] for s in sims if s["features"] is not None}
    y_t, scales = np.asarray(targets["features"]), np.asarray(targets["scales"])
    sets = {k: ("farthest_point" if k < 50 else "random") for k in range(len(y_t))}  # farthest_point+random
    data = DatasetStore("datasets/orange_peel_paper").arrays()
    stored = {tuple(np.round(t, 8)): y for t, y in zip(data.theta, data.y, strict=True)}
    scores: dict[str, dict[int, float]] = {}
    for r in rows:
        k, label = r["target_index"], r["optimizer"]
        if r["problem"] != "target":
            continue
        feats = memo.get(tuple(np.round(r["theta"], 10)))
        if feats is not None:
            scores.setdefault(label, {})[k] = float(recovery_reward(np.asarray(feats), y_t[k], scales))
    lookup_stored = {r["target_index"]: float(recovery_reward(stored[tuple(np.round(r["theta"], 8))],
                                                              y_t[r["target_index"]], scales))
                     for r in rows if r["optimizer"] == "nearest_neighbour" and r["problem"] == "target"}
    summary: dict = {"simulated_runs": len(sims), "targets": len(y_t), "methods": {}}
    ref = lookup_stored or scores.get("nearest_neighbour", {})
    for label, by_k in sorted(scores.items()):
        ks = sorted(by_k)
        a = np.array([by_k[k] for k in ks])
        entry = {"n": len(ks), "r_actual": mean_with_ci(a),
                 "by_set": {name: {"n": int(sum(sets[k] == name for k in ks)),
                                   "mean": float(np.mean([by_k[k] for k in ks if sets[k] == name]))}
                            for name in ("farthest_point", "random") if any(sets[k] == name for k in ks)}}
        both = [k for k in ks if k in ref]
        if label != "nearest_neighbour" and both:
            d = paired_difference(np.array([by_k[k] for k in both]), np.array([ref[k] for k in both]))
            entry["vs_nearest_neighbour"] = d
            entry["nearest_neighbour_on_same_targets"] = float(np.mean([ref[k] for k in both]))
        summary["methods"][label] = entry
    if lookup_stored:
        summary["methods"]["nearest_neighbour_stored_rows"] = {"n": len(lookup_stored),
                                                              "r_actual": mean_with_ci(np.array(list(lookup_stored.values())))}
    out.write_text(json.dumps(summary, indent=2))
    return summary


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1]), Path(sys.argv[2])), indent=2))
