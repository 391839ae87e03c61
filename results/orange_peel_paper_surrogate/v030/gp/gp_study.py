"""Gaussian-process regression against the shipped ensemble on the paper preset's 2,000 runs (issue 11).

    python results/orange_peel_paper_surrogate/v030/gp/gp_study.py --seed 0   # and 1, 2

Same rows as ``benchmarks/bench_simulator_surrogate.py --seed S`` (its ``split_rows``): 1,600 training
rows, 400 held-out rows used for R^2 only. Models, per split:

* ``ensemble``: the shipped :class:`EnsembleSurrogate` (defaults, seed S, as the benchmark builds it);
* ``gp``: 12 scikit-learn GPs, one per standardised feature, each its own kernel
  ``C * Matern(nu=2.5, ARD over the 9 parameters) + White``, hyperparameters by marginal likelihood
  (L-BFGS-B from length scales 0.5, no restarts) on all 1,600 training rows;
* ``average``: (ensemble + gp) / 2;
* ``blend_val``: w_j * gp + (1 - w_j) * ensemble with w_j in {0, 0.1, ..., 1} chosen per feature on the
  TRAINING rows only: the GP's exact leave-one-out predictions against the ensemble's out-of-fold ones
  (rows some member held out from its early-stopping carve; the ensemble mean of those members).

Writes ``split_S.json`` next to this file.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[3]
sys.path.insert(0, str(ROOT))


def bench():
    spec = importlib.util.spec_from_file_location("bench_simulator_surrogate",
                                                  ROOT / "benchmarks" / "bench_simulator_surrogate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def fit_gp(x: np.ndarray, z: np.ndarray, seed: int) -> dict:
    """One GP on a standardised target: test-time callable state, LOO predictions, kernel, time."""
    from scipy.linalg import cho_solve
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    kernel = (ConstantKernel(1.0, (1e-2, 1e2)) * Matern(np.full(x.shape[1], 0.5), (1e-2, 1e3), nu=2.5)
              + WhiteKernel(1e-2, (1e-5, 1.0)))
    t = time.time()
    gp = GaussianProcessRegressor(kernel, n_restarts_optimizer=0, random_state=seed).fit(x, z)
    kinv_diag = np.diag(cho_solve((gp.L_, True), np.eye(len(x))))
    loo = z - gp.alpha_ / kinv_diag
    return {"gp": gp, "loo": loo, "kernel": str(gp.kernel_), "lml": float(gp.log_marginal_likelihood_value_),
            "time_s": time.time() - t}


def load_split(seed: int) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Feature names and (x, y, xt, yt): the benchmark's training and held-out rows of split ``seed``."""
    from invphys.core.dataset import DatasetStore

    data = DatasetStore(ROOT / "datasets" / "orange_peel_paper").arrays(ok_only=True)
    tr, te = bench().split_rows(len(data.theta), seed)
    return list(data.feature_names), data.theta[tr], data.y[tr], data.theta[te], data.y[te]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    from joblib import Parallel, delayed

    from invphys.models.data import r2_scores, split_indices
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

    names, x, y, xt, yt = load_split(args.seed)
    mu, sd = y.mean(0), y.std(0)
    z = (y - mu) / sd
    out: dict = {"seed": args.seed, "n_train": len(x), "n_test": len(xt), "feature_names": names, "models": {}}

    t = time.time()
    ens = EnsembleSurrogate(seed=args.seed, val_fraction=0.1)
    ens.fit(x, y)
    ens_time = time.time() - t
    p_ens = ens.predict(xt)
    c = ens.config
    held = [split_indices(len(x), c.val_fraction, c.seed + k)[1] for k in range(c.members)]
    mask = np.zeros((c.members, len(x)), dtype=bool)
    for k, va in enumerate(held):
        mask[k, va] = True
    rows = np.flatnonzero(mask.any(axis=0))
    w = mask[:, rows, None]
    oof_ens = (ens._member_predict(x[rows]) * w).sum(axis=0) / w.sum(axis=0)
    print(f"ensemble {ens_time:.0f} s; {len(rows)} out-of-fold rows", flush=True)

    fits = Parallel(n_jobs=args.jobs)(delayed(fit_gp)(x, z[:, j], args.seed) for j in range(len(names)))
    p_gp = np.stack([f["gp"].predict(xt) for f in fits], axis=1) * sd + mu
    loo_gp = np.stack([f["loo"] for f in fits], axis=1) * sd + mu

    grid = np.round(np.linspace(0, 1, 11), 1)
    weights = []
    for j in range(len(names)):
        err = [np.mean((g * loo_gp[rows, j] + (1 - g) * oof_ens[:, j] - y[rows, j]) ** 2) for g in grid]
        weights.append(float(grid[int(np.argmin(err))]))
    wv = np.array(weights)
    preds = {"ensemble": p_ens, "gp": p_gp, "average": (p_ens + p_gp) / 2, "blend_val": wv * p_gp + (1 - wv) * p_ens}
    for label, p in preds.items():
        r2, per = r2_scores(yt, p)
        out["models"][label] = {"r2": r2, "r2_min_feature": min(per), "worst_feature": names[int(np.argmin(per))],
                                "r2_per_feature": dict(zip(names, per, strict=True))}
        print(f"{label}: R^2 {r2:.4f}, worst {min(per):.3f} ({names[int(np.argmin(per))]}); "
              + ", ".join(f"{v:.3f}" for v in per), flush=True)
    out["models"]["ensemble"]["train_time_s"] = ens_time
    out["models"]["gp"].update({"train_time_s": sum(f["time_s"] for f in fits),
                                "kernels": {n: f["kernel"] for n, f in zip(names, fits, strict=True)},
                                "loo_r2_per_feature": dict(zip(names, r2_scores(y, loo_gp)[1], strict=True))})
    out["models"]["blend_val"]["gp_weight"] = dict(zip(names, weights, strict=True))
    out["models"]["blend_val"]["validation_rows"] = len(rows)
    (HERE / f"split_{args.seed}.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
