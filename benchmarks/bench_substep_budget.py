"""What bounds the orange peel's time step, and what that means for GPU throughput (issue 16). CPU, no physics.

Each run's dt is the smallest of four bounds (:func:`invphys_anisompm.engine.dt_bounds`): the elastic CFL
``cfl * dx / c`` (c the run's wave speed), ``frame_dt / min_substeps_per_frame``, the damage regularisation
``eta_dt_factor * min(eta)`` and the grip's kinematic CFL. Over random parameter vectors this script counts which
bound binds, each bound's share of all substeps, the substeps per run with and without the eta bound, and the
useful particle-substeps a run costs; with ``--target-s`` it turns that into the kernel rate (particle-substeps
per second) a GPU must sustain for that many seconds per run, with no host time at all. The counts are the
engine's own estimate (:func:`estimated_substeps`, exact unless the velocity guard binds; on the GPU the 256
random runs of seed 0 averaged 5,828 substeps against an estimate of the same).

Example::

    python benchmarks/bench_substep_budget.py --preset paper --runs 2000 --target-s 0.15 \\
        --measured-rate 630e6 --out benchmarks/results/substep_budget_paper.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from _machine import emit  # noqa: E402


def substeps(dt_bound: np.ndarray, options, frames: int) -> np.ndarray:
    """Substeps per run (settling included) for a per-run dt bound: ceil(frame_dt / bound) per frame."""
    from invphys_anisompm.engine import frame_plan

    nsub, _ = frame_plan(options.fps, dt_bound)
    return (frames + round(options.settle_seconds * options.fps)) * nsub


def summary(v: np.ndarray) -> dict[str, float]:
    return {"mean": float(v.mean()), "median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "min": float(v.min()), "max": float(v.max())}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--runs", type=int, default=2000, help="random parameter vectors (uniform in the unit cube)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target-s", type=float, default=0.15, help="GPU seconds per run to translate into a rate")
    ap.add_argument("--measured-rate", type=float, default=None,
                    help="a measured kernel rate (useful particle-substeps/s) to project seconds per run from")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from invphys_anisompm.engine import dt_bounds
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    sim = OrangePeelSimulator(preset=args.preset, arch="cpu")
    scene, frames = sim.engine_scene, sim.frames
    options = scene.engine.options
    theta = np.random.default_rng(args.seed).random((args.runs, sim.parameter_space().dim))
    model = model_for(scene, sim.parameter_space().denormalize(theta))
    terms = dt_bounds(model, frames)
    table = np.stack(list(terms.values()), axis=1)
    binding = table.argmin(axis=1)
    full = substeps(table.min(axis=1), options, frames)
    no_eta = substeps(np.delete(table, list(terms).index("eta"), axis=1).min(axis=1), options, frames)
    particles = int(scene.engine.n_particles)
    work = full * particles
    names = sim.parameter_space().names
    corr = np.corrcoef(np.c_[theta, np.log(full)].T)[-1, :-1]
    out = {
        "benchmark": "substep_budget", "date": time.strftime("%Y-%m-%d"), "command": "python " + " ".join(sys.argv),
        "device": "none (host arithmetic: the engine's dt bounds and substep estimate)",
        "simulator": sim.name, "simulator_version": sim.version, "preset": args.preset,
        "config_hash": RunIdentity.of(sim).config, "frames": frames, "particles": particles, "runs": args.runs,
        "seed": args.seed,
        "options": {k: getattr(options, k) for k in ("cfl", "dx", "fps", "min_substeps_per_frame", "eta_dt_factor",
                                                      "kinematic_cfl", "settle_seconds")},
        "binding_bound": {name: {"runs": float((binding == i).mean()),
                                 "share_of_substeps": float(full[binding == i].sum() / full.sum())}
                          for i, name in enumerate(terms)},
        "substeps_per_run": summary(full),
        "substeps_per_run_without_eta_bound": summary(no_eta),
        "eta_bound_cost": float(full.sum() / no_eta.sum()),
        "useful_particle_substeps_per_run": float(work.mean()),
        "log_substeps_correlation": dict(zip(names, map(float, np.round(corr, 3)), strict=True)),
        "target_s_per_run": args.target_s,
        "rate_needed_for_target": float(work.mean() / args.target_s),
        "rate_needed_for_target_without_eta_bound": float(no_eta.mean() * particles / args.target_s),
    }
    if args.measured_rate:
        out["measured_rate"] = args.measured_rate
        out["kernel_s_per_run_at_measured_rate"] = float(work.mean() / args.measured_rate)
    emit(out, args.out)
    return out


if __name__ == "__main__":
    main()
