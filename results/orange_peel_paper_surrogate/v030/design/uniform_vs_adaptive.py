"""The adaptive store against uniform stores of the same size, all scored on the 2,000 uniform runs of
``datasets/orange_peel_paper`` (none of them trained on). CPU, the shipped ensemble (defaults).

    python results/orange_peel_paper_surrogate/v030/design/uniform_vs_adaptive.py

* ``uniform_block_k``: rows 1,600 k .. 1,600 (k + 1) of ``datasets/orange_peel_paper_seed1_v030`` in generation
  order (i.i.d. uniform, seed 1), k = 0..4: five disjoint uniform designs of 1,600 runs (ensemble seed 0);
* ``adaptive_seed_s``: all 1,600 rows of ``datasets/orange_peel_paper_adaptive`` (design seed 2), ensemble seeds
  0, 1, 2 (the spread of training alone);
* ``adaptive3_seed_s``: the same for ``datasets/orange_peel_paper_adaptive_seed3`` (a second realisation of the
  same adaptive settings, design seed 3).

Writes ``uniform_vs_adaptive.json`` next to this file.
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


def rows_in_order(path: Path):
    from invphys.core.dataset import DatasetStore

    store = DatasetStore(path)
    data = store.arrays(ok_only=True)
    order = np.argsort(store.frame(ok_only=True)["sample_index"].to_numpy(), kind="stable")
    return data.theta[order], data.y[order]


def main() -> None:
    from invphys.core.dataset import DatasetStore
    from invphys.models.data import r2_scores
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

    test = DatasetStore(ROOT / "datasets" / "orange_peel_paper").arrays(ok_only=True)
    names = list(test.feature_names)
    uni_x, uni_y = rows_in_order(ROOT / "datasets" / "orange_peel_paper_seed1_v030")
    ada_x, ada_y = rows_in_order(ROOT / "datasets" / "orange_peel_paper_adaptive")
    runs = {f"uniform_block_{k}": (uni_x[1600 * k:1600 * (k + 1)], uni_y[1600 * k:1600 * (k + 1)], 0) for k in range(5)}
    runs |= {f"adaptive_seed_{s}": (ada_x, ada_y, s) for s in range(3)}
    ada3_x, ada3_y = rows_in_order(ROOT / "datasets" / "orange_peel_paper_adaptive_seed3")
    runs |= {f"adaptive3_seed_{s}": (ada3_x, ada3_y, s) for s in range(3)}
    out_path = HERE / "uniform_vs_adaptive.json"
    out = json.loads(out_path.read_text()) if out_path.exists() else {}
    out.update({"command": "python " + " ".join(sys.argv), "test": "datasets/orange_peel_paper, all 2,000 rows",
                "feature_names": names})
    for label, (x, y, seed) in runs.items():
        if label in out.get("runs", {}):
            continue
        t = time.time()
        model = EnsembleSurrogate(seed=seed)
        model.fit(x, y)
        pred = model.predict(test.theta)
        r2, per = r2_scores(test.y, pred)
        out.setdefault("runs", {})[label] = {"r2": float(r2), "worst": float(min(per)),
                                             "worst_feature": names[int(np.argmin(per))],
                                             "r2_per_feature": dict(zip(names, map(float, per), strict=True)),
                                             "n_train": len(x), "time_s": round(time.time() - t, 1)}
        print(f"{label}: {r2:.4f} (worst {min(per):.3f} {names[int(np.argmin(per))]})", flush=True)
        out_path.write_text(json.dumps(out, indent=1) + "\n")
    uni = [v["r2"] for k, v in out["runs"].items() if k.startswith("uniform")]
    ada = [v["r2"] for k, v in out["runs"].items() if k.startswith("adaptive")]
    out["summary"] = {"uniform_mean": float(np.mean(uni)), "uniform_min": float(min(uni)), "uniform_max": float(max(uni)),
                      "adaptive_mean": float(np.mean(ada)), "adaptive_min": float(min(ada)), "adaptive_max": float(max(ada))}
    print(out["summary"])
    out_path.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
