"""The real simulator in the loop: what refining a lookup answer on the simulator costs and gains.

    python benchmarks/bench_simulator_loop.py [--targets 4] [--budget 16] [--popsize 5] [--arch cpu]
        [--preset tiny] [--out benchmarks/results/simulator_loop_tiny_cpu.json]

Targets are held-out rows of the committed fixture ``tests/data/orange_tiny.npz`` (512 tiny-preset
runs; 80/20 split, seed 0; farthest-point targets in the test rows). For each target:

1. the nearest-neighbour baseline answers from the training rows (no model, no simulation);
2. ask/tell CMA-ES (``invphys.evaluators.simulator_loop.refine_targets``) refines that answer
   on the real simulator: the start is simulated, then each generation of *every* target is one
   simulator batch, ``--budget`` runs per target in all;
3. the targets' features are those of today's simulator at the rows' true parameters (simulated
   once, so targets are reachable: the noise floor is 1 for a deterministic simulator); the fixture's
   own features (made by an earlier simulator build) are scored against them too, to show how far
   the lookup table's simulator is from today's. ``--fixture-targets`` uses the fixture's features as
   targets instead.

Records R_actual of the start and of the refined answer per target, simulator runs, wall time per
target, the device and the simulator version.
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", type=int, default=4)
    ap.add_argument("--budget", type=int, default=16, help="simulator runs per target (start included)")
    ap.add_argument("--popsize", type=int, default=5)
    ap.add_argument("--sigma0", type=float, default=0.1)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--fixture-targets", action="store_true", help="targets = the fixture's features")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "simulator_loop_tiny_cpu.json")
    args = ap.parse_args()

    from invphys import registry
    from invphys.core.objectives import percentile_scales, recovery_reward
    from invphys.core.target_selection import select_targets
    from invphys.evaluators.simulator_loop import SimulatorEvaluator, refine_targets
    from invphys.plugins.baselines import NearestNeighbour
    from invphys.plugins.validators.simulator import SimulatorValidator

    with np.load(ROOT / "tests" / "data" / "orange_tiny.npz") as f:
        theta, y, fixture_version = f["theta"], f["y"], str(f["simulator_version"])
    perm = np.random.default_rng(0).permutation(len(theta))
    n_test = round(0.2 * len(theta))
    test, train = np.sort(perm[:n_test]), np.sort(perm[n_test:])
    scales = percentile_scales(y[train])
    rows = select_targets(y, test, args.targets, "farthest_point")
    y_t = y[rows]
    nn = NearestNeighbour()
    nn.fit(theta[train], y[train], scales)
    starts = nn.answer(y_t).theta

    simulator = registry.create("simulator", {"type": "orange_peel", "preset": args.preset, "arch": args.arch,
                                              "backend": "taichi", "batch_size": 64})
    extractor = registry.create("feature_extractor", {"type": simulator.default_feature_extractor()})
    validator = SimulatorValidator(batch_size=max(64, args.targets * args.popsize))
    ev = SimulatorEvaluator.from_validator(validator, simulator, extractor)
    t0 = time.perf_counter()
    fresh = ev(theta[rows])
    floor_s = time.perf_counter() - t0
    fixture_vs_today = recovery_reward(y[rows], fresh, scales)
    if not args.fixture_targets:
        y_t = fresh
        starts = nn.answer(y_t).theta
    floor = recovery_reward(fresh, y_t, scales)
    ev.runs = ev.batches = 0
    ev.wall_time_s = 0.0
    t0 = time.perf_counter()
    refined = refine_targets(y_t, starts, scales, ev, args.budget, args.popsize, args.sigma0, seed=0)
    wall = time.perf_counter() - t0
    start_r = [r.history[0][1] for r in refined]
    out = {
        "benchmark": "bench_simulator_loop", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_simulator_loop.py " + " ".join(sys.argv[1:]),
        "simulator": simulator.name, "simulator_version": simulator.version, "fixture_simulator_version": fixture_version,
        "preset": args.preset, "arch": args.arch, "device": ev.device, "host": platform.node(),
        "targets": args.targets, "dataset_rows": rows.tolist(), "budget_runs_per_target": args.budget,
        "popsize": args.popsize, "sigma0": args.sigma0,
        "simulator_runs": ev.runs, "simulator_batches": ev.batches, "failed_runs": ev.failed,
        "wall_s": wall, "wall_per_target_s": wall / args.targets, "simulator_s_per_target": ev.wall_time_s / args.targets,
        "targets_from": "fixture" if args.fixture_targets else "today's simulator at the rows' true parameters",
        "noise_floor_r_actual": floor.tolist(), "noise_floor_wall_s": floor_s,
        "fixture_features_vs_today_r": fixture_vs_today.tolist(),
        "nearest_neighbour_r_actual": start_r, "refined_r_actual": [r.score for r in refined],
        "mean_nearest_neighbour": float(np.mean(start_r)), "mean_refined": float(np.mean([r.score for r in refined])),
        "mean_noise_floor": float(np.mean(floor)),
        "history": [[[int(e), float(s)] for e, s in r.history] for r in refined],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps({k: v for k, v in out.items() if k != "history"}, indent=1))


if __name__ == "__main__":
    main()
