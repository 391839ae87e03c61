"""Tiled against atomic P2G on a GPU (Taichi): same grid, same features, how much faster.

The tiled scatter (``taichi_p2g: tiled``, CUDA only) sums each tile of consecutive (Morton-ordered)
particles in shared memory before adding it to the grid; the atomic one adds every particle's share to
every node with global float atomics (``docs/gpu-throughput.md``). This benchmark, on ``--runs`` random
parameter vectors (seed 0) of the orange peel at ``--preset``:

1. **grid parity**: both backends load the same runs, set the same moving, strained, partly damaged state
   (``perturbed_state``) and do one P2G; the grids (momentum, mass, damage sums, grip mass) must agree to
   float rounding (the order of the sums differs; the tiled sums are fixed-point integers);
2. **kernel profile**: seconds per launch of each substep stage (``kernel_times``), both ways;
3. **whole runs**: the same runs simulated atomic, tiled, then atomic again, in lock-step batches of
   ``--batch``: wall time per run, the ratio to the paper's 156 s, and the features' agreement (median,
   90th percentile and worst relative difference per feature, and of the feature means) of tiled against
   atomic, next to atomic against atomic (GPU float atomics alone make two atomic runs differ).

    python examples/anisompm/benchmarks/bench_tiled_p2g.py --preset paper --runs 64 --batch 64 --out examples/anisompm/benchmarks/results/tiled_p2g_fixed_point_sums_paper_h100.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

PAPER_SECONDS_PER_RUN = 156.0


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--runs", type=int, default=64)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--frames", type=int, default=None, help="override the preset's frames (shorter runs)")
    p.add_argument("--skip-runs", action="store_true", help="grid parity and kernel profile only")
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def feature_agreement(x: np.ndarray, y: np.ndarray, names: list[str]) -> dict:
    """How closely features ``y`` (runs x features) follow ``x`` of the same runs: median, 90th percentile
    and worst relative difference per feature, and the relative difference of the feature means."""
    ok = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(y), axis=1)
    rel = np.abs(y[ok] - x[ok]) / np.maximum(np.abs(x[ok]), 1e-12)
    means = np.abs(y[ok].mean(0) - x[ok].mean(0)) / np.maximum(np.abs(x[ok].mean(0)), 1e-12)
    return {"runs_compared": int(ok.sum()), "median_rel_diff_all": float(np.median(rel)),
            "median_rel_diff": dict(zip(names, np.median(rel, axis=0).tolist(), strict=True)),
            "p90_rel_diff": dict(zip(names, np.percentile(rel, 90, axis=0).tolist(), strict=True)),
            "max_rel_diff": dict(zip(names, np.max(rel, axis=0).tolist(), strict=True)),
            "mean_of_feature_rel_diff": dict(zip(names, means.tolist(), strict=True))}


def timed_features(sim, params: np.ndarray, extractor) -> tuple[float, np.ndarray]:
    """Simulate ``params`` with ``sim`` after an untimed two-run pass (the whole path compiled): the wall
    seconds and the features per run (NaN rows for failed runs)."""
    sim.simulate(params[: min(2, len(params))])
    t0 = time.perf_counter()
    res = sim.simulate(params)
    wall = time.perf_counter() - t0
    nan = np.full(len(extractor.feature_names), np.nan)
    return wall, np.array([extractor.extract(r.trajectory) if r.ok else nan for r in res])


def perturbed_state(B: int, N: int, seed: int = 1) -> dict[str, np.ndarray]:
    """A moving, strained, partly damaged state of ``B`` runs of ``N`` particles (scene order): velocities
    ~0.1 m/s, deformation gradients 2 % from identity, APIC matrices, damage on a fifth of the particles.
    At rest every momentum is zero, which would leave the momentum sums untested."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    d = np.where(rng.uniform(size=(B, N)) < 0.2, rng.uniform(size=(B, N)), 0.0)
    return {"v": (0.1 * rng.standard_normal((B, N, 3))).astype(f32),
            "C": rng.standard_normal((B, N, 3, 3)).astype(f32),
            "F": (np.eye(3) + 0.02 * rng.standard_normal((B, N, 3, 3))).astype(f32),
            "d": d.astype(f32)}


def set_perturbed_state(backend, seed: int = 1) -> None:
    """Write ``perturbed_state`` (scene order) into ``backend``'s particle arrays, in the device's order."""
    perm = getattr(backend, "_perm", None)
    for name, values in perturbed_state(backend.batch, backend.scene.n_particles, seed).items():
        backend.set_particle_array(name, values if perm is None else values[:, perm])


def perturbed_frame(sim, params: np.ndarray, steps: int) -> Any:
    """The backend of ``sim`` with ``params``' runs loaded in ``perturbed_state`` (the same state whatever the
    device's particle order) and a frame of ``steps`` substeps set (dt 1e-4, grips still)."""
    from invphys_orange_peel.engine_scene import model_for

    B = len(params)
    backend = sim.engine.backend(B)
    model = model_for(sim.engine_scene, params)
    backend.load(model.table(), model.friction)
    set_perturbed_state(backend)
    nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
    backend.set_frame(np.full(B, 1e-4), np.full(B, steps), np.zeros((B, steps, nk, 6)), damage_on=True)
    return backend


def _grids(sim, params: np.ndarray) -> dict[str, np.ndarray]:
    """One clear + P2G of the loaded runs in ``perturbed_state``; the grid arrays in float64."""
    backend = perturbed_frame(sim, params, 2)
    stages = backend._stages(0)
    stages["clear"]()
    stages["p2g"]()
    backend.sync()
    return {k: getattr(backend, k).to_numpy().astype(np.float64) for k in ("gv", "gm", "gd", "gg")}


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.runs, space.dim)))
    cfg = {"backend": "taichi", "preset": a.preset, "arch": "cuda", "batch_size": a.batch}
    if a.frames:
        cfg["frames"] = a.frames
    sims = {mode: OrangePeelSimulator(**cfg, taichi_p2g=mode) for mode in ("atomic", "tiled")}
    out: dict = {"benchmark": "bench_tiled_p2g", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
                 "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
                 "simulator_version": RunIdentity.of(sims["atomic"]).version,
                 "config_hash": RunIdentity.of(sims["atomic"]).config, "preset": a.preset, "runs": a.runs,
                 "batch": a.batch, "frames": sims["atomic"].frames}
    out["device"] = sims["atomic"].engine.backend(min(a.batch, a.runs)).device

    g = {m: _grids(s, params[:a.batch]) for m, s in sims.items()}
    parity = {}
    for k in ("gv", "gm", "gd", "gg"):
        ref, new = g["atomic"][k], g["tiled"][k]
        scale = float(np.abs(ref).max()) or 1.0
        parity[k] = {"max_abs_diff_over_max": float(np.abs(new - ref).max() / scale),
                     "sum_rel_diff": float(abs(new.sum() - ref.sum()) / (abs(ref.sum()) or 1.0))}
    out["grid_parity"] = parity
    print("grid parity", json.dumps(parity), flush=True)

    out["kernel_seconds_per_substep"] = {}
    for m, s in sims.items():
        backend = s.engine.backend(a.batch)
        backend.kernel_times(3)  # warm
        out["kernel_seconds_per_substep"][m] = backend.kernel_times(20)
    kt = out["kernel_seconds_per_substep"]
    out["p2g_speedup"] = kt["atomic"]["p2g"] / kt["tiled"]["p2g"]
    out["substep_speedup"] = sum(kt["atomic"].values()) / sum(kt["tiled"].values())
    print("kernels", json.dumps(kt), f"p2g x{out['p2g_speedup']:.2f}, substep x{out['substep_speedup']:.2f}",
          flush=True)

    if not a.skip_runs:
        ex = OrangePeelFeatures()
        feats, walls = {}, {}
        # atomic twice: two atomic runs of the same parameters differ too (GPU float atomics, amplified by
        # fracture); that spread is the yardstick for tiled against atomic
        for m, s in (("atomic", sims["atomic"]), ("tiled", sims["tiled"]), ("atomic_again", sims["atomic"])):
            walls[m], feats[m] = timed_features(s, params, ex)
            print(m, f"{walls[m] / a.runs:.3f} s/run", flush=True)

        out["runs_result"] = {
            m: {"seconds_per_run": walls[m] / a.runs, "speedup_vs_paper_156s": PAPER_SECONDS_PER_RUN * a.runs / walls[m],
                "failed": int((~np.all(np.isfinite(feats[m]), axis=1)).sum())} for m in walls}
        out["runs_speedup_tiled_vs_atomic"] = (walls["atomic"] + walls["atomic_again"]) / 2 / walls["tiled"]
        out["feature_agreement"] = {"tiled_vs_atomic": feature_agreement(feats["atomic"], feats["tiled"], ex.feature_names),
                                    "atomic_vs_atomic": feature_agreement(feats["atomic"], feats["atomic_again"], ex.feature_names)}
        fa = out["feature_agreement"]
        print("runs", json.dumps(out["runs_result"]), "median rel diff tiled/atomic",
              fa["tiled_vs_atomic"]["median_rel_diff_all"], "atomic/atomic", fa["atomic_vs_atomic"]["median_rel_diff_all"],
              flush=True)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
