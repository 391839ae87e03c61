"""Benchmark the cheese-cut simulator (AnisoMPM engine): wall time per run, particle-substeps/s, runs/hour.

Examples::

    python benchmarks/bench_cheese_cut.py --preset tiny --runs 4 --batch 4 --arch cpu
    python benchmarks/bench_cheese_cut.py --preset quick --runs 512 --batch 256 --arch cuda

Runs ``--runs`` parameter vectors drawn uniformly in the normalised space (seed ``--seed``: what dataset
generation costs), ``--batch`` at a time (sorted by cost). A first batch of one run warms the kernels up
(compile time reported apart). ``--parity`` also runs the same vectors on the other backend and reports
the largest relative feature difference. Writes JSON to
``benchmarks/results/cheese_cut_<backend>_<preset>_<arch>[_<tag>].json`` (or ``--out``) with the device,
the simulator and engine versions and the command.
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
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "anisompm"), str(ROOT / "examples" / "cheese_cut"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="taichi", choices=["taichi", "warp"])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--runs", type=int, default=None, help="total runs (default: one batch)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--parity", action="store_true", help="also run the other backend and compare features")
    ap.add_argument("--tag", default="")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from invphys_anisompm import ENGINE_VERSION
    from invphys_cheese_cut import SIMULATOR_VERSION
    from invphys_cheese_cut.features import FEATURE_NAMES, CheeseCutFeatures
    from invphys_cheese_cut.simulator import CheeseCutSimulator

    runs = args.runs or args.batch
    sim = CheeseCutSimulator(backend=args.backend, preset=args.preset, arch=args.arch, batch_size=args.batch)
    space = sim.parameter_space()
    params = space.denormalize(np.random.default_rng(args.seed).uniform(size=(runs, space.dim)))
    t0 = time.perf_counter()
    sim.simulate(space.center()[None])  # compile / warm up on a batch of one
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    results = sim.simulate(params)
    wall = time.perf_counter() - t0
    n = sim.scene.n_particles
    ok = [r for r in results if r.ok]
    substeps = sum(r.stats.substeps for r in results)
    fe = CheeseCutFeatures()
    out = {
        "benchmark": "bench_cheese_cut", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python " + " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
        "simulator": "cheese_cut", "simulator_version": SIMULATOR_VERSION, "engine_version": ENGINE_VERSION,
        "backend": args.backend, "preset": args.preset, "arch": args.arch, "device": results[0].stats.device,
        "host": platform.node(), "particles": n, "runs": runs, "batch": args.batch, "seed": args.seed,
        "warmup_s": warm, "wall_s": wall, "wall_per_run_s": wall / runs, "runs_per_hour": 3600 * runs / wall,
        "ok_runs": len(ok), "failures": [r.failure for r in results if not r.ok],
        "substeps_mean": substeps / runs, "useful_particle_substeps_per_s": substeps * n / wall,
    }
    if args.parity:
        other = "warp" if args.backend == "taichi" else "taichi"
        sim2 = CheeseCutSimulator(backend=other, preset=args.preset, arch=args.arch, batch_size=args.batch)
        res2 = sim2.simulate(params)
        pairs = [(a, b) for a, b in zip(results, res2, strict=True) if a.ok and b.ok]
        fa = np.array([fe.extract(a.trajectory) for a, _ in pairs])
        fb = np.array([fe.extract(b.trajectory) for _, b in pairs])
        scale = np.maximum(np.abs(fa).max(axis=0), 1e-12)
        rel = np.abs(fa - fb) / scale
        out["parity"] = {"other_backend": other, "runs_compared": len(pairs),
                         "max_rel_diff_per_feature": dict(zip(FEATURE_NAMES, rel.max(axis=0).tolist(), strict=True)),
                         "median_rel_diff": float(np.median(rel))}
    path = args.out or ROOT / "benchmarks" / "results" / (
        f"cheese_cut_{args.backend}_{args.preset}_{args.arch}" + (f"_{args.tag}" if args.tag else "") + ".json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k not in ("failures",)}, indent=1))
    return out


if __name__ == "__main__":
    main()
