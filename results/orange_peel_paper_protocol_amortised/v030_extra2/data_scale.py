"""1,600 against 2,624 training rows on the same 100 targets (issue 17 item 6).

Both amortised runs (amortised_vs_lookup_paper.yaml, and amortised_vs_lookup_paper_extra.yaml after the
fix that keeps targets and scales those of `dataset.path`) answer the same 100 held-out targets, scored
with the same scales; every answer was re-simulated on an H100. Paired bootstrap intervals (2,000
resamples over targets) compare each method across data sizes and against the lookup at each size.
Reads the two committed run.tgz archives.
usage: python results/orange_peel_paper_protocol_amortised/v030_extra2/data_scale.py
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


def paired(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, n: int = 2000) -> list[float]:
    d = a - b
    boots = d[rng.integers(0, len(d), size=(n, len(d)))].mean(1)
    return [round(float(d.mean()), 4), round(float(np.percentile(boots, 2.5)), 4),
            round(float(np.percentile(boots, 97.5)), 4)]


def main() -> None:
    targets = {k: _read(p, "invert/targets.json") for k, p in RUNS.items()}
    if targets["1600"]["rows"] != targets["2624"]["rows"] or targets["1600"]["scales"] != targets["2624"]["scales"]:
        raise SystemExit("the two runs do not share their targets and scales")
    n = len(targets["1600"]["rows"])
    r: dict[tuple[str, str], np.ndarray] = {}
    for k, p in RUNS.items():
        by = {(x["optimizer"], x["target_index"]): x for x in _read(p, "validate/validation.json")
              if x["problem"] == "target"}
        for m in METHODS:
            r[k, m] = np.array([by[m, i]["r_actual"] if by[m, i].get("r_actual") is not None else 0.0
                                for i in range(n)])
    rng = np.random.default_rng(0)
    out = {"targets": n, "mean_R_actual": {k: {m: round(float(r[k, m].mean()), 4) for m in METHODS} for k in RUNS},
           "vs_nearest_neighbour": {k: {m: paired(r[k, m], r[k, "nearest_neighbour"], rng) for m in METHODS[1:]}
                                    for k in RUNS},
           "2624_minus_1600": {m: paired(r["2624", m], r["1600", m], rng) for m in METHODS},
           "note": "[mean, 2.5 %, 97.5 %] of paired differences over targets"}
    (HERE / "data_scale.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
