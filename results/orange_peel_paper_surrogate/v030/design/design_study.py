"""Does the choice of the 1,600 training runs matter? A pool study for issue 11 (CPU only, no simulation).

    python results/orange_peel_paper_surrogate/v030/design/design_study.py --seed 0 --designs random,sobol,active

The test rows are split ``seed``'s 400 held-out rows of ``datasets/orange_peel_paper`` (uniform random
parameters), as in ``benchmarks/bench_simulator_surrogate.py``. The pool is every other stored paper-preset
run of simulator 0.3.0: that split's 1,600 training rows plus the 8,000 rows of
``datasets/orange_peel_paper_seed1_v030`` (9,600 runs). Each design picks 1,600 pool rows, i.e. what a
2,000-run budget would have simulated had it chosen its parameters that way (1,600 training + 400 test);
the shipped ensemble (defaults, seed ``seed``) is trained on them and scored on the same 400 test rows.

Designs:

* ``random``: 1,600 pool rows at random (rng ``seed + 100``): i.i.d. uniform, today's datasets;
* ``sobol``: 1,600 scrambled Sobol points in [0, 1]^9, each matched to its nearest unused pool row
  (greedy, in Sobol order): an approximate space-filling design;
* ``active``: 800 random pool rows, then 4 rounds of 200: fit the ensemble, take the pool rows whose
  members disagree most (sum over features of the members' std / the feature's training std), at least
  ``min_gap`` apart in parameter space so a round does not pile onto one spot.

Writes ``split_S.json`` (per design: mean and per-feature R^2, the chosen rows' coverage) next to this file.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[3]
sys.path.insert(0, str(ROOT))

N_TRAIN = 1600


def load(seed: int):
    import importlib.util

    from invphys.core.dataset import DatasetStore

    spec = importlib.util.spec_from_file_location("bss", ROOT / "benchmarks" / "bench_simulator_surrogate.py")
    bss = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bss)
    main = DatasetStore(ROOT / "datasets" / "orange_peel_paper").arrays(ok_only=True)
    extra = DatasetStore(ROOT / "datasets" / "orange_peel_paper_seed1_v030").arrays(ok_only=True)
    assert list(main.feature_names) == list(extra.feature_names)
    tr, te = bss.split_rows(len(main.theta), seed)
    pool_x = np.concatenate([main.theta[tr], extra.theta])
    pool_y = np.concatenate([main.y[tr], extra.y])
    return list(main.feature_names), pool_x, pool_y, main.theta[te], main.y[te]


def fit(x, y, seed):
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

    s = EnsembleSurrogate({"seed": seed})
    s.fit(x, y)
    return s


def score(s, xt, yt, names):
    from invphys.models.data import r2_scores

    r2, per = r2_scores(yt, s.predict(xt))
    return {"r2": float(r2), "r2_per_feature": dict(zip(names, map(float, per), strict=True)),
            "worst": float(min(per)), "worst_feature": names[int(np.argmin(per))]}


def design_random(pool_x, seed):
    return np.random.default_rng(seed + 100).choice(len(pool_x), N_TRAIN, replace=False)


def design_sobol(pool_x, seed):
    from scipy.stats import qmc

    pts = qmc.Sobol(d=pool_x.shape[1], scramble=True, seed=seed).random(2048)[:N_TRAIN]
    free = np.ones(len(pool_x), bool)
    chosen = []
    for p in pts:
        d = ((pool_x - p) ** 2).sum(1)
        d[~free] = np.inf
        i = int(np.argmin(d))
        free[i] = False
        chosen.append(i)
    return np.array(chosen)


def design_active(pool_x, pool_y, seed, rounds=4, start=800, min_gap=0.15):
    rng = np.random.default_rng(seed + 100)
    chosen = list(rng.choice(len(pool_x), start, replace=False))
    per_round = (N_TRAIN - start) // rounds
    for r in range(rounds):
        s = fit(pool_x[chosen], pool_y[chosen], seed + 1000 + r)
        _, std = s.predict_with_uncertainty(pool_x)
        scale = pool_y[chosen].std(0)
        u = (std / scale).sum(1)
        u[chosen] = -np.inf
        picked: list[int] = []
        for i in np.argsort(-u):
            if len(picked) == per_round:
                break
            if picked and np.sqrt(((pool_x[picked] - pool_x[i]) ** 2).sum(1)).min() < min_gap:
                continue
            picked.append(int(i))
        chosen += picked
        print(f"  active round {r + 1}: +{len(picked)} rows, mean u of picked {u[picked].mean():.3f} "
              f"(pool median {np.median(u[np.isfinite(u)]):.3f})", flush=True)
    return np.array(chosen)


def coverage(x):
    """Smallest pairwise distance (median over rows) and the fraction of rows near the box's faces."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(x).query(x, k=2)
    return {"median_nn_distance": float(np.median(d[:, 1])),
            "near_face_fraction": float((np.minimum(x, 1 - x).min(1) < 0.05).mean())}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--designs", default="random,sobol,active")
    ap.add_argument("--initial", type=int, default=800, help="active: random rows first")
    ap.add_argument("--rounds", type=int, default=4, help="active: rounds for the other rows")
    args = ap.parse_args()
    names, pool_x, pool_y, xt, yt = load(args.seed)
    out_path = HERE / f"split_{args.seed}.json"
    out = json.loads(out_path.read_text()) if out_path.exists() else {}
    out.update({"seed": args.seed, "pool_rows": len(pool_x), "test_rows": len(xt), "train_rows": N_TRAIN,
                "command": "python " + " ".join(sys.argv)})
    for name in args.designs.split(","):
        t = time.time()
        if name == "random":
            rows = design_random(pool_x, args.seed)
        elif name == "sobol":
            rows = design_sobol(pool_x, args.seed)
        elif name == "active":
            rows = design_active(pool_x, pool_y, args.seed, rounds=args.rounds, start=args.initial)
            if (args.initial, args.rounds) != (800, 4):
                name = f"active_{args.initial}_{args.rounds}"
        else:
            raise SystemExit(f"unknown design {name!r}")
        assert len(set(rows.tolist())) == N_TRAIN
        s = fit(pool_x[rows], pool_y[rows], args.seed)
        res = score(s, xt, yt, names) | coverage(pool_x[rows]) | {"time_s": round(time.time() - t, 1)}
        out.setdefault("designs", {})[name] = res
        print(f"{name}: R2 {res['r2']:.4f}, worst {res['worst']:.3f} ({res['worst_feature']}), "
              f"nn {res['median_nn_distance']:.3f}, {res['time_s']} s", flush=True)
        out_path.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
