"""How learnable a stored simulator dataset is: held-out R^2 of the MLP and the 5-member ensemble.

    python benchmarks/bench_simulator_surrogate.py datasets/orange_peel_paper \\
        --out benchmarks/results/simulator_surrogate_paper.json

Split: 80/20 of the ok rows (seeded permutation), the held-out 20 % also being the early-stopping set
(the paper's protocol, as in bench_surrogate.py). Reports overall and per-feature R^2 of
:class:`MLPSurrogate` and :class:`EnsembleSurrogate` (paper defaults), and the MLP's learning curve on
``--curve`` training-set sizes (same held-out rows).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "examples" / "orange_peel")]


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--curve", default="250,500,1000,1600")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)

    import torch

    from invphys.core.dataset import DatasetStore
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    store = DatasetStore(args.dataset)
    data = store.arrays(ok_only=True)
    names = list(data.feature_names)
    n = len(data.theta)
    perm = np.random.default_rng(args.seed).permutation(n)
    te, tr = np.sort(perm[: round(0.2 * n)]), np.sort(perm[round(0.2 * n):])
    tt, yt, tv, yv = data.theta[tr], data.y[tr], data.theta[te], data.y[te]
    out: dict = {
        "benchmark": "bench_simulator_surrogate",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_simulator_surrogate.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "dataset": str(args.dataset), "identity": store.metadata.get("identity"), "fingerprint": data.fingerprint,
        "n_train": len(tt), "n_test": len(tv), "feature_names": names,
        "machine": {"platform": platform.platform(), "torch": torch.__version__, "threads": torch.get_num_threads()},
        "models": {},
    }
    for label, model in (("mlp", MLPSurrogate(seed=args.seed)), ("ensemble", EnsembleSurrogate(seed=args.seed))):
        m = model.fit(tt, yt, validation=(tv, yv))
        out["models"][label] = {"r2": m["r2"], "epochs": m["epochs"], "train_time_s": m["train_time_s"],
                                "r2_per_feature": dict(zip(names, m["r2_per_feature"], strict=True))}
        print(f"{label}: R^2 {m['r2']:.4f}; " + ", ".join(f"{k} {v:.3f}" for k, v in
                                                          out["models"][label]["r2_per_feature"].items()), flush=True)
    curve = []
    for size in (int(s) for s in args.curve.split(",")):
        size = min(size, len(tt))
        idx = np.random.default_rng(100).permutation(len(tt))[:size]
        m = MLPSurrogate(seed=args.seed).fit(tt[idx], yt[idx], validation=(tv, yv))
        curve.append({"n_train": size, "r2": m["r2"], "r2_min_feature": float(min(m["r2_per_feature"]))})
        print(f"curve {size}: R^2 {m['r2']:.4f}", flush=True)
    out["learning_curve_mlp"] = curve
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
