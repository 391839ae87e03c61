"""Optimiser costs on this machine vs the paper: GC-PPO training, inversion latency, CMA-ES, env throughput.

    python benchmarks/bench_optimizers.py [--steps 20480] [--out benchmarks/results/optimizers_cpu.json]

All measurements use the real MLP surrogate (the paper's 256-256-128 skip MLP) trained on the committed
orange-peel fixture ``tests/data/orange_tiny.npz`` (512 tiny-preset runs), in the raw [0, 1]^9 space:

* GC-PPO training throughput with the paper's PPO settings (8 envs, 256 steps per env per update,
  batch 64, 10 epochs, 2x256 MLP) for ``--steps`` steps; extrapolated to 500k steps vs the paper's
  ~9 min;
* inversion latency: a trained policy's deterministic 8-step rollout (8 surrogate calls of 1 point +
  8 policy forwards), median over held-out targets, vs the paper's ~10 ms;
* CMA-ES with 5,000 evaluations (popsize 20) and the 540-evaluation warm start, per target (paper:
  warm start ~0.16 s);
* surrogate evaluations per second inside the vectorised env (8 and 64 envs, random actions), and the
  bare surrogate's batched throughput for reference.

Torch runs with ``--threads`` CPU threads (default 1, the optimisers' default).
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
PAPER = {"gc_ppo_train_500k_s": 9 * 60, "inversion_8_steps_s": 0.010, "warm_start_540_s": 0.16,
         "surrogate_call_s": 0.13e-3}


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=20_480, help="GC-PPO training steps to time (>= 20k)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--targets", type=int, default=5, help="held-out targets for the CMA-ES timings")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "optimizers_cpu.json")
    args = ap.parse_args()

    import torch

    from invphys.core.objectives import RecoveryObjective, percentile_scales, recovery_reward
    from invphys.core.spaces import build_problem, make_predict, raw_space
    from invphys.envs.task import InverseTask
    from invphys.envs.vec import InverseVecEnv
    from invphys.plugins.optimizers import CMAES, GoalConditionedPPO, WarmStart
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    torch.set_num_threads(args.threads)
    with np.load(ROOT / "tests" / "data" / "orange_tiny.npz") as f:
        theta, y = f["theta"].astype(np.float64), f["y"].astype(np.float64)
    perm = np.random.default_rng(0).permutation(len(theta))
    test_idx, train_idx = np.sort(perm[: len(theta) // 5]), np.sort(perm[len(theta) // 5:])
    t0 = time.perf_counter()
    surrogate = MLPSurrogate(max_epochs=200, patience=30, seed=0)
    surrogate.fit(theta[train_idx], y[train_idx], validation=(theta[test_idx], y[test_idx]))
    fit_s = time.perf_counter() - t0
    scales = percentile_scales(y[train_idx])
    mean, std = y[train_idx].mean(axis=0), y[train_idx].std(axis=0)
    space = raw_space(9)
    predict = make_predict(space, surrogate)
    results: dict = {"machine": {"platform": platform.platform(), "python": sys.version.split()[0],
                                 "cpus": os.cpu_count(), "torch": torch.__version__, "torch_threads": args.threads,
                                 "loadavg_start": os.getloadavg()},
                     "surrogate": {"r2_test": surrogate.metrics.get("r2"), "fit_s": fit_s,
                                   "n_train": len(train_idx)},
                     "paper": PAPER}

    # -- bare surrogate ------------------------------------------------------------------------
    one = _median_time(lambda: surrogate.predict(theta[:1]), 300)
    batch = _median_time(lambda: surrogate.predict(theta[:256]), 50)
    results["surrogate_call"] = {"one_point_s": one, "batch256_s": batch, "batch256_evals_per_s": 256 / batch,
                                 "ratio_one_point_vs_paper": one / PAPER["surrogate_call_s"]}
    print(f"surrogate: 1 point {one * 1e3:.3f} ms, 256 points {batch * 1e3:.3f} ms", flush=True)

    # -- vectorised env throughput ---------------------------------------------------------------
    env_rates = {}
    y_tr = y[train_idx]
    for n_envs in (8, 64):
        task = InverseTask(low=0.0, high=1.0, dim=9, predict=predict,
                           score=lambda yy, g: recovery_reward(yy, g, scales),
                           feature_mean=mean, feature_std=std,
                           goal_sampler=lambda rng, n: y_tr[rng.integers(0, len(y_tr), n)])
        env = InverseVecEnv(task, n_envs=n_envs, seed=0)
        env.reset()
        rng = np.random.default_rng(0)
        acts = rng.uniform(-1, 1, size=(400, n_envs, 9)).astype(np.float32)
        t0 = time.perf_counter()
        for a in acts:
            env.step(a)
        dt = time.perf_counter() - t0
        env_rates[str(n_envs)] = {"steps": len(acts), "surrogate_calls": env.predict_calls,
                                  "evals_per_s": len(acts) * n_envs / dt, "env_steps_per_s": len(acts) / dt}
        print(f"vec env {n_envs} envs: {len(acts) * n_envs / dt:,.0f} surrogate evaluations/s "
              f"({env.predict_calls} batched calls)", flush=True)
    results["vec_env"] = env_rates

    # -- GC-PPO training ---------------------------------------------------------------------------
    gc = GoalConditionedPPO(total_timesteps=args.steps, seed=0, torch_threads=args.threads)
    metrics = gc.prepare(space, predict, y_tr, scales)
    extrap = 500_000 / metrics["steps_per_s"]
    results["gc_ppo_train"] = {**metrics, "config": gc.config.model_dump(),
                               "extrapolated_500k_s": extrap,
                               "ratio_vs_paper": extrap / PAPER["gc_ppo_train_500k_s"]}
    print(f"gc_ppo: {metrics['timesteps']} steps in {metrics['train_time_s']:.1f} s = "
          f"{metrics['steps_per_s']:.0f} steps/s -> 500k in {extrap / 60:.1f} min (paper ~9 min)", flush=True)

    # -- inversion latency ------------------------------------------------------------------------
    lat, scores = [], []
    for i in test_idx:
        problem = build_problem(space, RecoveryObjective(y[i], scales), 8, surrogate=surrogate, target=y[i])
        t0 = time.perf_counter()
        res = gc.optimize(problem)
        lat.append(time.perf_counter() - t0)
        scores.append(res.score)
    results["inversion"] = {"targets": len(lat), "median_s": float(np.median(lat)), "p90_s": float(np.percentile(lat, 90)),
                            "mean_r_surrogate": float(np.mean(scores)),
                            "ratio_vs_paper": float(np.median(lat)) / PAPER["inversion_8_steps_s"]}
    print(f"inversion (8 steps): median {np.median(lat) * 1e3:.2f} ms (paper ~10 ms), "
          f"mean R_surr {np.mean(scores):.3f} after {metrics['timesteps']} training steps", flush=True)

    # -- CMA-ES 5000 and warm start 540 -----------------------------------------------------------
    cma_t, cma_s, ws_t, ws_s = [], [], [], []
    for i in test_idx[: args.targets]:
        p = build_problem(space, RecoveryObjective(y[i], scales), 5000, surrogate=surrogate, target=y[i], seed=int(i))
        t0 = time.perf_counter()
        r = CMAES(budget=5000).optimize(p)
        cma_t.append(time.perf_counter() - t0)
        cma_s.append(r.score)
        p = build_problem(space, RecoveryObjective(y[i], scales), 540, surrogate=surrogate, target=y[i], seed=int(i))
        t0 = time.perf_counter()
        r = WarmStart().attach(gc).optimize(p)
        ws_t.append(time.perf_counter() - t0)
        ws_s.append(r.score)
    results["cma_es_5000"] = {"targets": len(cma_t), "median_s": float(np.median(cma_t)),
                              "mean_r_surrogate": float(np.mean(cma_s))}
    results["warm_start_540"] = {"targets": len(ws_t), "median_s": float(np.median(ws_t)),
                                 "mean_r_surrogate": float(np.mean(ws_s)),
                                 "ratio_vs_paper": float(np.median(ws_t)) / PAPER["warm_start_540_s"]}
    print(f"cma_es 5000 evals: median {np.median(cma_t):.2f} s (mean R_surr {np.mean(cma_s):.3f}); "
          f"warm start 540: median {np.median(ws_t):.3f} s (paper ~0.16 s, mean R_surr {np.mean(ws_s):.3f})",
          flush=True)
    results["machine"]["loadavg_end"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2, default=float))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
