"""1,600 against 2,624 training rows on the targets both amortised runs share (issue 17 item 6).

The 2,624-row run (amortised_vs_lookup_paper_extra.yaml) picked 73 of the 100 targets of the 1,600-row run
(amortised_vs_lookup_paper.yaml): farthest-point selection works in features scaled by the training rows'
p95 - p5, and the extra rows moved those scales by up to 5 %. On the shared targets, every answer's
simulated features are scored again with the 1,600-row run's scales (one yardstick), and paired bootstrap
intervals (2,000 resamples over targets) compare the methods. Reads the two committed run.tgz archives.
usage: python results/orange_peel_paper_protocol_amortised/v030_extra/shared_targets.py
"""
from __future__ import annotations

import json
import tarfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
RUNS = {"1600": HERE.parent / "v030" / "run.tgz", "2624": HERE / "run.tgz"}
METHODS = ["nearest_neighbour", "npe_surrogate", "corrected_search"]


def _read(tgz: Path, member: str) -> object:
    with tarfile.open(tgz) as tar:
        return json.load(tar.extractfile(member))


def reward(y: np.ndarray, target: np.ndarray, scales: np.ndarray, kappa: float = 3.0) -> float:
    z = (y - target) / scales
    return float(np.exp(-kappa * np.sqrt(np.mean(z * z))))


def paired(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, n: int = 2000) -> tuple[float, float, float]:
    d = a - b
    boots = d[rng.integers(0, len(d), size=(n, len(d)))].mean(1)
    return float(d.mean()), float(np.percentile(boots, 2.5)), float(np.percentile(boots, 97.5))


def main() -> None:
    targets = {k: _read(p, "invert/targets.json") for k, p in RUNS.items()}
    rows = {k: _read(p, "validate/validation.json") for k, p in RUNS.items()}
    scales = np.asarray(targets["1600"]["scales"])
    index = {k: {row: i for i, row in enumerate(t["rows"])} for k, t in targets.items()}
    shared = [row for row in targets["1600"]["rows"] if row in index["2624"]]
    feats = {row: np.asarray(targets["1600"]["features"][index["1600"][row]]) for row in shared}
    r: dict[tuple[str, str], np.ndarray] = {}
    for k in RUNS:
        by = {(x["optimizer"], x["target_index"]): x for x in rows[k]}
        for m in METHODS:
            r[k, m] = np.array([reward(np.asarray(by[m, index[k][row]]["actual"]), feats[row], scales) for row in shared])
    rng = np.random.default_rng(0)
    out = {"shared_targets": len(shared), "scales": "the 1,600-row run's", "mean_R_actual": {}, "vs_nearest_neighbour": {},
           "2624_minus_1600": {}}
    for k in RUNS:
        out["mean_R_actual"][k] = {m: round(float(r[k, m].mean()), 4) for m in METHODS}
        out["vs_nearest_neighbour"][k] = {m: [round(x, 4) for x in paired(r[k, m], r[k, "nearest_neighbour"], rng)]
                                          for m in METHODS[1:]}
    out["2624_minus_1600"] = {m: [round(x, 4) for x in paired(r["2624", m], r["1600", m], rng)] for m in METHODS}
    (HERE / "shared_targets.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
