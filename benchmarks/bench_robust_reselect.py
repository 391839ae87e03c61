"""Robust re-selection of simulator-in-the-loop answers: keep an answer only if it reproduces.

A polish (``bench_polish_from_lookup.py``) answers each target with its best simulated point, and
``--recheck K`` re-simulates those answers. On a chaotic simulator a few selected points do not
reproduce: the selecting run was lucky (best-of-N optimism). This benchmark takes the targets whose
recheck fell more than ``--tol`` below the selected R, re-simulates the target's ``--candidates`` best
logged points ``--k`` times each (round 1) and picks the candidate with the best mean re-simulated R;
every other target keeps its answer. Round 2 then simulates EVERY final answer ``--k`` more times, and
those fresh runs alone score it: no run that chose or kept an answer scores it. The JSON compares the
selected (best-of-N) mean, the plain recheck mean and the fresh mean of the re-selected answers, each
with bootstrap intervals, paired against the nearest-neighbour lookup; the answers go to
``<out>.answers.npz`` (theta, fresh R).

    # POLISH: a bench_polish_from_lookup.py result made with --recheck; LOG: its --log
    python benchmarks/bench_robust_reselect.py --polish POLISH --log LOG --arch cuda --out reselect.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--polish", type=Path, required=True, help="bench_polish_from_lookup JSON made with --recheck")
    p.add_argument("--log", type=Path, required=True, help="that polish's batch log (.npz)")
    p.add_argument("--recheck", type=Path, default=None, help="its .recheck.npz (default: next to --polish)")
    p.add_argument("--tol", type=float, default=0.01, help="re-select where a recheck fell this far below")
    p.add_argument("--candidates", type=int, default=8, help="best logged points re-simulated per target")
    p.add_argument("--k", type=int, default=2, help="runs per candidate (round 1) and for the pick (round 2)")
    p.add_argument("--arch", default=None)
    p.add_argument("--sim-batch", type=int, default=None)
    p.add_argument("--scheduling", default=None, choices=["lockstep", "continuous"])
    p.add_argument("--min-chunk", type=int, default=None)
    p.add_argument("--preset", default=None, help="simulator preset override (tests: tiny)")
    p.add_argument("--out", type=Path, required=True)
    return p.parse_args(argv)


def _assign(points: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Index of the start each logged point belongs to (the polish's steps stay near their start)."""
    return np.abs(points[:, None, :] - starts[None, :, :]).max(axis=2).argmin(axis=1)


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys.core.dataset import RunIdentity
    from invphys.core.objectives import recovery_reward
    from invphys.evaluation.stats import mean_with_ci, paired_difference
    from invphys.evaluators.simulator_loop import SimulatorEvaluator
    from invphys.inverter import load_inverter

    pj = json.loads(a.polish.read_text())
    if "recheck" not in pj:
        raise SystemExit(f"{a.polish} has no recheck: run bench_polish_from_lookup.py with --recheck K first")
    report = json.loads(Path(pj["report"]).read_text())
    inv = load_inverter(Path(pj["bundle"]))
    space = inv.parameter_space
    n = pj["targets"]
    targets = np.asarray(report["targets"]["features"], dtype=np.float64)[:n]
    scales = np.asarray(report["targets"]["scales"], dtype=np.float64)
    per = pj["per_target"]
    final = np.array([p["final"] for p in per])
    lookup = np.array([p["lookup"] for p in per])
    theta_final = space.normalize(np.array([p["theta"] for p in per]))
    rc = np.load(a.recheck or a.polish.with_suffix(".recheck.npz"))
    r_re = np.asarray(rc["r"], dtype=np.float64)  # (n, K) recheck R of each final answer

    # the polish's starts: the --start label's answers in the report
    rows = {r["target_index"]: r for r in report["rows"] if r["optimizer"] == pj["start"]}
    starts = space.normalize(np.array([[rows[i][f"param_{k}"] for k in space.names] for i in range(n)]))
    with np.load(a.log) as z:
        log_theta, log_y = np.asarray(z["theta"]), np.asarray(z["y"])
    polished = np.array([p["polished"] for p in per])
    owner = np.flatnonzero(polished)[_assign(log_theta, starts[polished])]
    log_r = np.full(len(log_theta), -np.inf)
    ok = np.all(np.isfinite(log_y), axis=1)
    log_r[ok] = recovery_reward(log_y[ok], targets[owner[ok]], scales)

    flagged = np.flatnonzero(np.nanmin(r_re, axis=1) < final - a.tol)
    cands: list[np.ndarray] = []
    for i in flagged:
        mine = np.flatnonzero(owner == i)
        best = mine[np.argsort(-log_r[mine])[:a.candidates]]
        pts = log_theta[best]
        if not np.any(np.abs(pts - theta_final[i]).max(axis=1) < 1e-12):
            pts = np.vstack([theta_final[i], pts])[:a.candidates]  # the answer itself (unpolished targets)
        cands.append(pts)

    overrides = {k: v for k, v in (("arch", a.arch), ("batch_size", a.sim_batch), ("preset", a.preset),
                                   ("scheduling", a.scheduling), ("min_chunk", a.min_chunk)) if v}
    sim = inv.simulator(overrides)
    validator = inv.bundle.registry.create("validator", {"type": "simulator", "batch_size": 256})
    evaluator = SimulatorEvaluator.from_validator(validator, sim, inv.extractor(sim))

    def r_of(points: np.ndarray, tgt: np.ndarray) -> np.ndarray:
        y = np.asarray(evaluator(points), dtype=np.float64)
        good = np.all(np.isfinite(y), axis=1)
        return np.where(good, recovery_reward(np.nan_to_num(y), tgt, scales), np.nan)

    t0 = time.perf_counter()
    picks, round1 = {}, {}
    if len(flagged):
        pts = np.vstack([np.repeat(c, a.k, axis=0) for c in cands])
        tg = np.vstack([np.repeat(targets[[i]], len(c) * a.k, axis=0) for i, c in zip(flagged, cands, strict=True)])
        r1 = r_of(pts, tg)
        at = 0
        for i, c in zip(flagged, cands, strict=True):
            block = r1[at:at + len(c) * a.k].reshape(len(c), a.k)
            at += len(c) * a.k
            means = np.array([np.mean(b[np.isfinite(b)]) if np.isfinite(b).any() else -np.inf for b in block])
            picks[int(i)], round1[int(i)] = c[int(np.argmax(means))], block
    answers = theta_final.copy()
    for i, pt in picks.items():
        answers[i] = pt
    fresh = r_of(np.repeat(answers, a.k, axis=0), np.repeat(targets, a.k, axis=0)).reshape(n, a.k)
    seconds = time.perf_counter() - t0
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(a.out.with_suffix(".answers.npz"), theta=space.denormalize(answers), r_fresh=fresh,
             flagged=np.asarray(flagged, dtype=np.int64),
             round1=np.concatenate([round1[int(i)] for i in flagged]) if len(flagged) else np.zeros((0, a.k)),
             round1_candidates=np.array([len(round1[int(i)]) for i in flagged], dtype=np.int64))

    est_recheck = np.nanmean(r_re, axis=1)
    est_robust = np.nanmean(fresh, axis=1)
    kept = np.setdiff1d(np.arange(n), flagged)

    out = {
        "benchmark": "bench_robust_reselect",
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
        "device": evaluator.device,
        "simulator_version": inv.bundle.manifest["simulator"]["version"],
        "config_hash": RunIdentity.of(sim).config,
        "polish": str(a.polish), "settings": {"tol": a.tol, "candidates": a.candidates, "k": a.k},
        "targets": n, "flagged": [int(i) for i in flagged],
        "runs": evaluator.runs, "simulator_seconds": evaluator.wall_time_s, "wall_s": seconds,
        "r_actual": {"lookup": mean_with_ci(lookup), "selected_best_of_n": mean_with_ci(final),
                     "recheck": mean_with_ci(est_recheck), "reselected_fresh": mean_with_ci(est_robust)},
        "vs_lookup": {"recheck": paired_difference(est_recheck, lookup),
                      "reselected_fresh": paired_difference(est_robust, lookup)},
        "fresh_minus_recheck": paired_difference(est_robust, est_recheck),
        "kept_fresh_minus_recheck": paired_difference(est_robust[kept], est_recheck[kept]),
        "per_flagged": [{"index": int(i), "selected": float(final[i]), "recheck": r_re[i].tolist(),
                         "candidates": len(round1[int(i)]),
                         "round1_best_mean": float(np.nanmax(np.nanmean(round1[int(i)], axis=1))),
                         "fresh": fresh[i].tolist(),
                         "theta": space.denormalize(picks[int(i)][None])[0].tolist()} for i in flagged],
    }
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    m = out["r_actual"]
    print(f"{len(flagged)} re-selected; best-of-N {m['selected_best_of_n']['mean']:.4f}, recheck "
          f"{m['recheck']['mean']:.4f}, fresh {m['reselected_fresh']['mean']:.4f} {m['reselected_fresh']['ci95']}; "
          f"{evaluator.runs} runs, {evaluator.wall_time_s:.0f} simulator-s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
