"""Issue 11's surrogate bar, measured on every uniform paper-preset run we hold: the shipped ensemble trained on
all 2,000 runs of each adaptive store, scored on the 10,000 uniform runs of ``datasets/orange_peel_paper`` (2,000)
and ``datasets/orange_peel_paper_seed1_v030`` (8,000), none of which it trained on. Five times the test rows of
``uniform_vs_adaptive.py`` (which scores on the first 2,000 only): a narrower interval on the same question.

    python results/orange_peel_paper_surrogate/v030/design/bar_check_10k.py

Ensemble seeds 0, 1, 2 per store (CPU, ~50 s each). Per fit: mean R^2 over the 12 features, each feature's R^2,
and a 95 % bootstrap interval of the mean R^2 over the test rows (1,000 resamples of the rows). Writes
``bar_check_10k.json`` next to this file.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from uniform_vs_adaptive import bootstrap_r2, rows_in_order  # noqa: E402

STORES = {"adaptive2000": "orange_peel_paper_adaptive", "adaptive3_2000": "orange_peel_paper_adaptive_seed3"}
TEST = ("orange_peel_paper", "orange_peel_paper_seed1_v030")


def main() -> None:
    from invphys.core.dataset import DatasetStore
    from invphys.models.data import r2_scores
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

    parts = [DatasetStore(ROOT / "datasets" / name).arrays(ok_only=True) for name in TEST]
    names = list(parts[0].feature_names)
    test_x = np.concatenate([p.theta for p in parts])
    test_y = np.concatenate([p.y for p in parts])
    out_path = HERE / "bar_check_10k.json"
    out = {"command": "python " + " ".join(sys.argv), "test": f"{', '.join(TEST)}: all {len(test_x):,} ok rows",
           "n_test": len(test_x), "feature_names": names, "bar": [0.95, 0.85], "runs": {}}
    for label, store in STORES.items():
        x, y = rows_in_order(ROOT / "datasets" / store)
        for seed in range(3):
            t = time.time()
            model = EnsembleSurrogate(seed=seed)
            model.fit(x, y)
            pred = model.predict(test_x)
            r2, per = r2_scores(test_y, pred)
            out["runs"][f"{label}_seed_{seed}"] = {
                "store": f"datasets/{store}", "n_train": len(x), "seed": seed, "r2": float(r2),
                "r2_ci95": bootstrap_r2(test_y, pred), "worst": float(min(per)),
                "worst_feature": names[int(np.argmin(per))],
                "r2_per_feature": dict(zip(names, map(float, per), strict=True)), "time_s": round(time.time() - t, 1)}
            print(f"{label} seed {seed}: {r2:.4f} {out['runs'][f'{label}_seed_{seed}']['r2_ci95']} "
                  f"(worst {min(per):.3f})", flush=True)
            out_path.write_text(json.dumps(out, indent=1) + "\n")
    r = [v["r2"] for v in out["runs"].values()]
    out["summary"] = {"min": float(min(r)), "max": float(max(r)), "mean": float(np.mean(r)),
                      "worst_feature_min": float(min(v["worst"] for v in out["runs"].values()))}
    print(out["summary"])
    out_path.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
