"""Benchmark the orange-peel simulator: wall time per run, particle-substeps/s, runs per hour.

Examples::

    python benchmarks/bench_simulator.py --preset tiny --batch 4 --arch cpu
    python benchmarks/bench_simulator.py --preset paper --runs 128 --batch 32 --arch cuda --spread

Runs ``--runs`` parameter vectors drawn uniformly in the normalised space (seed ``--seed``; that is
what dataset generation costs) or the centre (``--params centre``), in batches of ``--batch``
(sorted by dt). Reports compile/warm-up time separately. ``--spread`` repeats the first batch and
reports the largest feature and position differences (run-to-run spread; 0 on CPU). ``--profile``
times each substep kernel at the batch's shape. Writes JSON to
``benchmarks/results/simulator_<backend>_<preset>_<arch>[_<tag>].json`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)

PAPER_SECONDS_PER_RUN = 156.0  # the paper's simulator, 8 CPU threads


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", default="taichi", choices=["taichi", "warp"])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--batch", type=int, default=4, help="runs advanced together")
    ap.add_argument("--runs", type=int, default=None, help="total runs (default: one batch)")
    ap.add_argument("--params", default="random", choices=["random", "centre"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=None, help="override the preset's frame count")
    ap.add_argument("--nondeterministic", action="store_true", help="parallel CPU scatter (faster, not bitwise)")
    ap.add_argument("--spread", action="store_true", help="repeat the first batch and measure differences")
    ap.add_argument("--profile", action="store_true", help="time each substep kernel")
    ap.add_argument("--config", default="{}", help="JSON of simulator settings to override, e.g. "
                                                   "'{\"eta_dt_factor\": 1000}' (no eta bound)")
    ap.add_argument("--tag", default="")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator

    runs = args.runs or args.batch
    cfg = dict(backend=args.backend, preset=args.preset, arch=args.arch, batch_size=args.batch,
               deterministic=not args.nondeterministic)
    if args.frames:
        cfg["frames"] = args.frames
    cfg.update(json.loads(args.config))
    sim = OrangePeelSimulator(**cfg)
    space = sim.parameter_space()
    if args.params == "centre":
        params = np.repeat(space.center()[None], runs, axis=0)
    else:
        params = space.denormalize(np.random.default_rng(args.seed).uniform(size=(runs, space.dim)))
    n = sim.scene.n_particles

    t0 = time.perf_counter()  # compile the kernels and allocate the batch on the warm engine: one frame
    sim.engine.run(model_for(sim.engine_scene, params[: min(args.batch, runs)]), 1, 1)
    warmup_s = time.perf_counter() - t0
    useful0, launched0 = sim.engine.counters.useful, sim.engine.counters.launched

    t0 = time.perf_counter()
    results = sim.simulate(params)
    wall = time.perf_counter() - t0
    ex = OrangePeelFeatures()
    ok = [r for r in results if r.ok]
    substeps = np.array([r.stats.substeps for r in results])
    # lock-step cost: the engine's slot-substep counters (each frame launches its slowest member's substeps)
    launched = sim.engine.counters.launched - launched0
    useful = sim.engine.counters.useful - useful0
    device = results[0].stats.device
    out = {
        "benchmark": "bench_simulator",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python " + " ".join([Path(sys.argv[0]).name if argv is None else "bench_simulator.py",
                                         *(sys.argv[1:] if argv is None else argv)]),
        "backend": args.backend, "preset": args.preset, "arch": args.arch, "device": device,
        "simulator_version": sim.version, "config": sim.config.model_dump(mode="json"),
        "host": {"cpus": os.cpu_count(), "machine": platform.machine(), "python": platform.python_version()},
        "particles": n, "frames": sim.frames, "runs": runs, "batch": args.batch, "params": args.params,
        "seed": args.seed, "deterministic": not args.nondeterministic,
        "warmup_compile_s": warmup_s,
        "wall_s": wall,
        "wall_per_run_s": wall / runs,
        "runs_per_hour": 3600.0 * runs / wall,
        "substeps_per_run": {"mean": float(substeps.mean()), "min": int(substeps.min()),
                             "max": int(substeps.max())},
        "useful_particle_substeps_per_s": float(substeps.sum() * n / wall),
        "launched_particle_substeps_per_s": float(launched * n / wall),
        "lockstep_efficiency": float(useful / max(launched, 1)),
        "speedup_vs_paper_156s": PAPER_SECONDS_PER_RUN / (wall / runs),
        "failed": [r.failure for r in results if not r.ok],
        "ok_runs": len(ok),
        "materials_wave_speed_mps": {"mean": float(model_for(sim.engine_scene, params).wave_speed().mean())},
    }
    if args.spread:
        first = params[: args.batch]
        again = OrangePeelSimulator(**cfg).simulate(first)
        fd, pd_ = [], []
        for a, b in zip(results[: len(first)], again, strict=True):
            if a.ok and b.ok:
                fa, fb = ex.extract(a.trajectory), ex.extract(b.trajectory)
                fd.append(np.abs(fa - fb) / np.maximum(np.abs(fa), 1e-12))
                pd_.append(float(np.abs(a.trajectory.positions - b.trajectory.positions).max()))
        out["spread"] = {
            "runs_compared": len(fd),
            "max_abs_position_diff_m": max(pd_) if pd_ else None,
            "max_rel_feature_diff": float(np.max(fd)) if fd else None,
            "max_rel_feature_diff_per_feature": dict(zip(ex.feature_names, np.max(fd, axis=0).tolist(),
                                                         strict=True)) if fd else None,
        }
    if args.profile:
        B = min(args.batch, runs)
        backend = sim.engine.backend(B)
        model = model_for(sim.engine_scene, params[:B])
        backend.load(model.table(), model.friction)
        nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
        backend.set_frame(np.full(B, 1e-4), np.full(B, 1000), np.zeros((B, 1000, nk, 6)), damage_on=True)
        times = backend.kernel_times(20)
        per_substep = sum(times.values())
        out["kernel_seconds_per_substep"] = times
        out["profiled_particle_substeps_per_s"] = B * n / per_substep
    path = args.out or ROOT / "benchmarks" / "results" / (
        f"simulator_{args.backend}_{args.preset}_{args.arch}" + (f"_{args.tag}" if args.tag else "") + ".json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
