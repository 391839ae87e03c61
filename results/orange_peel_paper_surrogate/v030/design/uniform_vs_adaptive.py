"""Adaptive stores against uniform stores of the same size, all scored on the 2,000 uniform runs of
``datasets/orange_peel_paper`` (none of them trained on). CPU, the shipped ensemble (defaults) and, where said,
the paper MLP (``MLPSurrogate`` defaults).

    python results/orange_peel_paper_surrogate/v030/design/uniform_vs_adaptive.py

1,600 training runs (800 uniform + 4 adaptive rounds of 200):

* ``uniform_block_k``: rows 1,600 k .. 1,600 (k + 1) of ``datasets/orange_peel_paper_seed1_v030`` in generation
  order (i.i.d. uniform, seed 1), k = 0..4: five disjoint uniform designs of 1,600 runs (ensemble seed 0);
* ``adaptive_seed_s``: the first 1,600 rows (generation order) of ``datasets/orange_peel_paper_adaptive`` (design
  seed 2), ensemble seeds 0, 1, 2 (the spread of training alone);
* ``adaptive3_seed_s``: the same for ``datasets/orange_peel_paper_adaptive_seed3`` (a second realisation of the
  same adaptive settings, design seed 3).

2,000 training runs (the same stores grown by rounds 5 and 6; the issue's 2,000-run budget spent on training):

* ``uniform2000_block_k``: rows 2,000 k .. 2,000 (k + 1) of the seed-1 store, k = 0..3 (ensemble seed 0);
* ``adaptive2000_seed_s``, ``adaptive3_2000_seed_s``: all 2,000 rows of each adaptive store, ensemble seeds 0-2;
* ``..._mlp_paper``: the paper MLP on the 2,000-run designs (uniform blocks and both adaptive stores, seed 0).

Each run records the mean R^2, its worst feature and (the 2,000-run ones) a 95 % bootstrap interval of the mean R^2 over the 2,000
test rows (1,000 resamples of the rows; the interval of the test sample, not of training).

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


def bootstrap_r2(y: np.ndarray, pred: np.ndarray, resamples: int = 1000) -> list[float]:
    """95 % percentile interval of the mean-over-features R^2 over resamples of the test rows."""
    from invphys.models.data import r2_scores

    rng = np.random.default_rng(0)
    vals = [r2_scores(y[i], pred[i])[0] for i in (rng.integers(0, len(y), len(y)) for _ in range(resamples))]
    return [float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))]


def main() -> None:
    from invphys.core.dataset import DatasetStore
    from invphys.models.data import r2_scores
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    test = DatasetStore(ROOT / "datasets" / "orange_peel_paper").arrays(ok_only=True)
    names = list(test.feature_names)
    uni_x, uni_y = rows_in_order(ROOT / "datasets" / "orange_peel_paper_seed1_v030")
    ada_x, ada_y = rows_in_order(ROOT / "datasets" / "orange_peel_paper_adaptive")
    ada3_x, ada3_y = rows_in_order(ROOT / "datasets" / "orange_peel_paper_adaptive_seed3")
    ens, mlp = "ensemble", "mlp_paper"
    runs = {f"uniform_block_{k}": (uni_x[1600 * k:1600 * (k + 1)], uni_y[1600 * k:1600 * (k + 1)], 0, ens)
            for k in range(5)}
    runs |= {f"adaptive_seed_{s}": (ada_x[:1600], ada_y[:1600], s, ens) for s in range(3)}
    runs |= {f"adaptive3_seed_{s}": (ada3_x[:1600], ada3_y[:1600], s, ens) for s in range(3)}
    blocks = {f"uniform2000_block_{k}": (uni_x[2000 * k:2000 * (k + 1)], uni_y[2000 * k:2000 * (k + 1)]) for k in range(4)}
    runs |= {label: (x, y, 0, ens) for label, (x, y) in blocks.items()}
    runs |= {f"adaptive2000_seed_{s}": (ada_x[:2000], ada_y[:2000], s, ens) for s in range(3)}
    runs |= {f"adaptive3_2000_seed_{s}": (ada3_x[:2000], ada3_y[:2000], s, ens) for s in range(3)}
    blocks |= {"adaptive2000": (ada_x[:2000], ada_y[:2000]), "adaptive3_2000": (ada3_x[:2000], ada3_y[:2000])}
    runs |= {f"{label}_mlp_paper": (x, y, 0, mlp) for label, (x, y) in blocks.items()}
    out_path = HERE / "uniform_vs_adaptive.json"
    out = json.loads(out_path.read_text()) if out_path.exists() else {}
    out.update({"command": "python " + " ".join(sys.argv), "test": "datasets/orange_peel_paper, all 2,000 rows",
                "feature_names": names})
    for label, (x, y, seed, kind) in runs.items():
        if label in out.get("runs", {}):  # kept from an earlier run (the 1,600-run ones have no interval)
            continue
        t = time.time()
        model = EnsembleSurrogate(seed=seed) if kind == ens else MLPSurrogate(seed=seed)
        model.fit(x, y)
        pred = model.predict(test.theta)
        r2, per = r2_scores(test.y, pred)
        out.setdefault("runs", {})[label] = {"r2": float(r2), "worst": float(min(per)),
                                             "worst_feature": names[int(np.argmin(per))],
                                             "r2_per_feature": dict(zip(names, map(float, per), strict=True)),
                                             "r2_ci95": bootstrap_r2(test.y, pred), "model": kind,
                                             "n_train": len(x), "time_s": round(time.time() - t, 1)}
        print(f"{label}: {r2:.4f} (worst {min(per):.3f} {names[int(np.argmin(per))]})", flush=True)
        out_path.write_text(json.dumps(out, indent=1) + "\n")
    out["summary"] = {}
    for n_train in (1600, 2000):
        for group in ("uniform", "adaptive"):
            v = [r["r2"] for k, r in out["runs"].items()
                 if k.startswith(group) and r["n_train"] == n_train and r.get("model", ens) == ens]
            out["summary"][f"{group}_{n_train}"] = {"n": len(v), "mean": float(np.mean(v)), "min": float(min(v)),
                                                   "max": float(max(v))}
    print(out["summary"])
    out_path.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
