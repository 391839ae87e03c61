"""A GP on the shipped ensemble's cross-fitted residuals (stacking), paper preset, issue 11.

    python results/orange_peel_paper_surrogate/v030/gp/residual_study.py --seed 0   # and 1, 2

Same rows as ``benchmarks/bench_simulator_surrogate.py --seed S``. Per split:

* ``ensemble``: the shipped :class:`EnsembleSurrogate` (defaults, seed S) on all 1,600 training rows;
* out-of-fold ensemble predictions for every training row: 5 folds of the training rows, an ensemble
  (same settings, seed S + 100 + fold) fit on the other 4 folds predicts the held fold;
* ``ensemble_plus_gp``: ensemble + a GP fit on the out-of-fold residuals (y - oof), one per feature
  (``C * Matern(nu=2.5, ARD) + White`` on residual / feature std, marginal likelihood, no restarts).
  A GP that finds no structure in the residuals puts its variance into the white noise and predicts ~0;
* ``bagged``: mean of the full ensemble and the 5 fold ensembles' held-out predictions (30 networks;
  separates "more networks" from "the GP's correction").

Writes ``residual_split_S.json`` next to this file. Held-out rows are used for R^2 only.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from gp_study import HERE, fit_gp, load_split


def fold_fit(x, y, xt, tr, va, seed):
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

    ens = EnsembleSurrogate(seed=seed, val_fraction=0.1, threads=1)
    ens.fit(x[tr], y[tr])
    return ens.predict(x[va]), ens.predict(xt)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    from joblib import Parallel, delayed

    from invphys.models.data import r2_scores
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

    names, x, y, xt, yt = load_split(args.seed)
    sd = y.std(0)
    t = time.time()
    ens = EnsembleSurrogate(seed=args.seed, val_fraction=0.1)
    ens.fit(x, y)
    p_ens = ens.predict(xt)
    folds = np.array_split(np.random.default_rng(1000 + args.seed).permutation(len(x)), 5)
    jobs = [(np.sort(np.concatenate([f for i, f in enumerate(folds) if i != k])), np.sort(folds[k]))
            for k in range(5)]
    res = Parallel(n_jobs=args.jobs)(delayed(fold_fit)(x, y, xt, a, b, args.seed + 100 + k)
                                     for k, (a, b) in enumerate(jobs))
    oof = np.empty_like(y)
    for (_, va), (p_va, _) in zip(jobs, res, strict=True):
        oof[va] = p_va
    ens_time = time.time() - t
    print(f"ensembles {ens_time:.0f} s; out-of-fold R^2 {r2_scores(y, oof)[0]:.4f}", flush=True)
    resid = (y - oof) / sd
    fits = Parallel(n_jobs=args.jobs)(delayed(fit_gp)(x, resid[:, j], args.seed) for j in range(len(names)))
    corr = np.stack([f["gp"].predict(xt) for f in fits], axis=1) * sd
    loo = np.stack([f["loo"] for f in fits], axis=1)
    # fraction of the out-of-fold residual variance the GP explains, leave-one-out (training rows only)
    explained = 1 - ((resid - loo) ** 2).sum(0) / (resid ** 2).sum(0)
    preds = {"ensemble": p_ens, "ensemble_plus_gp": p_ens + corr,
             "bagged": (p_ens + sum(p for _, p in res)) / 6}
    out: dict = {"seed": args.seed, "n_train": len(x), "n_test": len(xt), "feature_names": names,
                 "oof_r2_per_feature": dict(zip(names, r2_scores(y, oof)[1], strict=True)),
                 "ensembles_time_s": ens_time, "models": {}}
    for label, p in preds.items():
        r2, per = r2_scores(yt, p)
        out["models"][label] = {"r2": r2, "r2_min_feature": min(per), "worst_feature": names[int(np.argmin(per))],
                                "r2_per_feature": dict(zip(names, per, strict=True))}
        print(f"{label}: R^2 {r2:.4f}, worst {min(per):.3f} ({names[int(np.argmin(per))]}); "
              + ", ".join(f"{v:.3f}" for v in per), flush=True)
    out["models"]["ensemble_plus_gp"].update({
        "gp_time_s": sum(f["time_s"] for f in fits),
        "kernels": {n: f["kernel"] for n, f in zip(names, fits, strict=True)},
        "loo_explained_residual_variance": dict(zip(names, explained.tolist(), strict=True))})
    print("LOO explained residual variance: " + ", ".join(f"{v:.3f}" for v in explained), flush=True)
    (HERE / f"residual_split_{args.seed}.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
