"""Warp CUDA on the AnisoMPM engine against the committed Taichi-CUDA cheese-cut dataset.

Re-simulates the first N rows of ``datasets/cheese_cut_quick`` with the Warp backend on CUDA and writes
the throughput and, per feature, the median and largest differences to the stored (Taichi) features,
relative to the feature's largest |value| (GPU atomics make neither backend bit-reproducible).

Usage, from the repository root on a GPU machine with warp-lang::

    python benchmarks/bench_cheese_cut_gpu_parity.py --runs 256 --out benchmarks/results/cheese_cut_warp_quick_cuda.json
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT / "examples" / "anisompm"), str(ROOT / "examples" / "cheese_cut"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=256)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "cheese_cut_warp_quick_cuda.json")
    args = ap.parse_args(argv)

    import pandas as pd
    from invphys_cheese_cut.features import FEATURE_NAMES, CheeseCutFeatures
    from invphys_cheese_cut.parameters import PARAMETER_NAMES
    from invphys_cheese_cut.simulator import CheeseCutSimulator

    parts = sorted(glob.glob(str(ROOT / "datasets" / "cheese_cut_quick" / "part-*.parquet")))
    df = pd.concat(pd.read_parquet(f) for f in parts).iloc[:args.runs]
    params = df[["p_" + k for k in PARAMETER_NAMES]].to_numpy()
    stored = df[["f_" + k for k in FEATURE_NAMES]].to_numpy()
    n = len(params)
    sim = CheeseCutSimulator(backend="warp", preset="quick", arch="cuda", batch_size=n)
    t0 = time.perf_counter()
    sim.simulate(params[:1])
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = sim.simulate(params)
    wall = time.perf_counter() - t0
    fe = CheeseCutFeatures()
    ok = [i for i, r in enumerate(res) if r.ok]
    feats = np.array([fe.extract(res[i].trajectory) for i in ok])
    rel = np.abs(feats - stored[ok]) / np.abs(stored).max(axis=0)
    report = {
        "command": "python benchmarks/bench_cheese_cut_gpu_parity.py --runs " + str(args.runs),
        "device": res[0].stats.device, "backend": "warp", "preset": "quick", "runs": n, "ok": len(ok),
        "warmup_s": warm, "wall_s": wall, "runs_per_hour": 3600 * n / wall,
        "substeps_mean": float(np.mean([r.stats.substeps for r in res])),
        "useful_particle_substeps_per_s": sum(r.stats.substeps for r in res) * sim.scene.n_particles / wall,
        "vs_taichi_cuda_dataset": {
            "median_rel_diff_per_feature": dict(zip(FEATURE_NAMES, np.median(rel, 0).tolist(), strict=True)),
            "max_rel_diff_per_feature": dict(zip(FEATURE_NAMES, rel.max(0).tolist(), strict=True)),
            "note": "relative to each feature's largest |value|; GPU atomics are not deterministic"},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    return report


if __name__ == "__main__":
    main()
