"""Simulator-in-the-loop polish started from the nearest-neighbour lookup, on a protocol's targets.

The cheapest refined method: answer each target with its nearest training row (the lookup, no
surrogate), then run ask/tell CMA-ES on the real simulator from that row
(:func:`invphys.evaluators.polish.polish`, the function behind ``active.polish`` and
``invphys invert --polish``) on the targets whose lookup R_actual is below ``--below``. No surrogate,
no active learning, no retraining: what does the simulator alone buy per run?

``--start LABEL`` starts from another method's validated answers in the same report instead (e.g.
``active_polished``: a further polish of an earlier refined run). Such answers have no stored
features, so each polished start is simulated once more: its re-simulated R against the report's
validated R is recorded (``start_resimulated``), a check of the best-of-N selection's optimism.

Inputs: a protocol ``report.json`` (its 100 targets and the lookup's validated answers) and the inverter
bundle that was trained on the same split (its ``data/train.npz`` holds the lookup rows' stored
features, so the starts are not simulated again; its recorded simulator config is used, with
``--arch`` and ``--sim-batch`` overrides). Every simulated chunk is logged to ``--log`` and replayed by
a re-run, so a time-limited GPU job resumes where the last one stopped. The JSON records the device,
simulator version and config hash, the command, mean R_actual with bootstrap intervals, the paired
difference against the lookup, per set (farthest-point / random), per generation, and the cost.

    # REPORT, BUNDLE: a protocol run's report/report.json and the bundle trained on the same split
    python benchmarks/bench_polish_from_lookup.py --report REPORT \\
        --bundle BUNDLE --arch cuda --log runs/polish_lookup/log.npz \\
        --out benchmarks/results/polish_from_lookup_paper_h100.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--report", type=Path, required=True, help="protocol report.json (targets, lookup answers)")
    p.add_argument("--start", default="nearest_neighbour", help="label in the report whose answers are polished")
    p.add_argument("--bundle", type=Path, required=True, help="inverter bundle trained on the same split")
    p.add_argument("--budget", type=int, default=24, help="new simulator runs per polished target")
    p.add_argument("--popsize", type=int, default=8)
    p.add_argument("--sigma0", type=float, default=0.012, help="CMA-ES step in the normalised cube")
    p.add_argument("--below", type=float, default=0.9, help="polish targets whose start R_actual is below")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--arch", default=None, help="simulator arch override (cuda, cpu)")
    p.add_argument("--sim-batch", type=int, default=None, help="simulator launch width override")
    p.add_argument("--scheduling", default=None, choices=["lockstep", "continuous"],
                   help="simulator scheduling override (not part of the run identity)")
    p.add_argument("--min-chunk", type=int, default=None, help="continuous: fewest substeps per host round trip")
    p.add_argument("--chunk", type=int, default=200, help="rows per simulator call (a stop loses one chunk)")
    p.add_argument("--preset", default=None, help="simulator preset override (tests: tiny)")
    p.add_argument("--targets", type=int, default=None, help="first N targets only (smoke runs)")
    p.add_argument("--log", type=Path, required=True, help="batch log (.npz): replayed by a re-run")
    p.add_argument("--compare", type=Path, default=None, help="another report.json on the same targets: "
                   "its labels' per-target R_actual are compared (e.g. the active + polish run)")
    p.add_argument("--recheck", type=int, default=0, metavar="K",
                   help="simulate every final answer K more times, independently of the search (best-of-N "
                        "optimism: the answer's R was measured by the very run that selected it)")
    p.add_argument("--out", type=Path, required=True)
    return p.parse_args(argv)


def _starts(report: dict, label: str, space, train: dict, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A label's answers (normalised theta), validated R_actual and, where an answer is a training row, its
    stored features (NaN otherwise: polish() simulates such a start once)."""
    rows = {r["target_index"]: r for r in report["rows"] if r["optimizer"] == label}
    if len(rows) < n:
        labels = sorted({r["optimizer"] for r in report["rows"]})
        raise SystemExit(f"{label!r} answers {len(rows)} of {n} targets in the report (labels: {', '.join(labels)})")
    names = space.names
    phys = np.array([[rows[i][f"param_{k}"] for k in names] for i in range(n)])
    theta = space.normalize(phys)
    r_val = np.array([rows[i]["r_actual"] for i in range(n)], dtype=np.float64)
    d = np.abs(train["theta"][None, :, :] - theta[:, None, :]).max(axis=2)
    j = d.argmin(axis=1)
    found = d[np.arange(n), j] < 1e-6
    feats = np.where(found[:, None], train["y"][j], np.nan)
    return theta, r_val, feats


class _FirstCall:
    """Passes calls through to a BatchLog and keeps the first call's features (the re-simulated starts)."""

    def __init__(self, inner) -> None:
        self.inner, self.first = inner, None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        out = self.inner(points)
        if self.first is None:
            self.first = np.array(out, dtype=np.float64)
        return out

    def __getattr__(self, name: str):
        return getattr(self.inner, name)


def _recheck(k: int, evaluator, theta: np.ndarray, targets: np.ndarray, scales: np.ndarray, final: np.ndarray,
             r_lookup: np.ndarray, path: Path) -> dict:
    """Re-simulate the final answers ``k`` times (fresh runs, no log): mean R per target and its spread."""
    from invphys.core.objectives import recovery_reward
    from invphys.evaluation.stats import mean_with_ci, paired_difference

    n = len(theta)
    t0 = time.perf_counter()
    y = np.asarray(evaluator(np.repeat(theta, k, axis=0)), dtype=np.float64).reshape(n, k, -1)
    seconds = time.perf_counter() - t0
    ok = np.all(np.isfinite(y), axis=2)
    r = np.where(ok, recovery_reward(np.nan_to_num(y).reshape(n * k, -1), np.repeat(targets, k, axis=0),
                                     scales).reshape(n, k), np.nan)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, theta=theta, y=y, r=r)
    r_mean = np.nanmean(np.where(ok, r, np.nan), axis=1)
    dif = r - final[:, None]
    return {"k": k, "runs": n * k, "failed": int((~ok).sum()), "seconds": seconds, "features": str(path.name),
            "r_actual_resimulated": mean_with_ci(r_mean),
            "resimulated_minus_selected": {"mean": float(np.nanmean(dif)), "median_abs": float(np.nanmedian(np.abs(dif))),
                                           "targets_below_by_0.01": int((np.nanmin(dif, axis=1) < -0.01).sum()),
                                           "worst": float(np.nanmin(dif))},
            "vs_lookup": paired_difference(r_mean, r_lookup),
            "per_target": [[float(x) for x in row] for row in r]}


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys.core.dataset import RunIdentity
    from invphys.core.objectives import recovery_reward
    from invphys.evaluation.stats import mean_with_ci, paired_difference
    from invphys.evaluators.polish import BatchLog, polish
    from invphys.evaluators.simulator_loop import SimulatorEvaluator
    from invphys.inverter import load_inverter

    report = json.loads(a.report.read_text())
    inv = load_inverter(a.bundle)
    space = inv.parameter_space
    tg = report["targets"]
    targets = np.asarray(tg["features"], dtype=np.float64)
    n = len(targets) if a.targets is None else min(a.targets, len(targets))
    targets = targets[:n]
    scales = np.asarray(inv.bundle.scales, dtype=np.float64)
    if not np.allclose(scales, tg["scales"], rtol=1e-9):
        raise SystemExit("the bundle's feature scales differ from the report's: not the same split")
    with np.load(a.bundle / "data" / "train.npz") as z:
        train = {"theta": z["theta"], "y": z["y"]}
    theta0, r_given, feats0 = _starts(report, a.start, space, train, n)
    r_lookup = _starts(report, "nearest_neighbour", space, train, n)[1]
    r_start = recovery_reward(np.nan_to_num(feats0), targets, scales)
    r_start = np.where(np.all(np.isfinite(feats0), axis=1), r_start, np.nan)

    overrides = {k: v for k, v in (("arch", a.arch), ("batch_size", a.sim_batch), ("preset", a.preset),
                                   ("scheduling", a.scheduling), ("min_chunk", a.min_chunk)) if v}
    sim = inv.simulator(overrides)
    ext = inv.extractor(sim)
    validator = inv.bundle.registry.create("validator", {"type": "simulator", "batch_size": a.chunk})
    evaluator = SimulatorEvaluator.from_validator(validator, sim, ext)
    settings = {"budget": a.budget, "popsize": a.popsize, "sigma0": a.sigma0, "below": a.below, "seed": a.seed}
    # the log is keyed on the physics (the run identity), not on how runs are scheduled on the device
    # and not on the budget: the seeded searches ask the same points, so a larger budget simulates only the
    # extra generations and a smaller one replays the first ones
    keyed = {k: v for k, v in settings.items() if k != "budget"}
    key = hashlib.sha256(json.dumps({"targets": targets.tolist(), "starts": theta0.tolist(), **keyed,
                                     "sim": RunIdentity.of(sim).to_dict()},
                                    sort_keys=True).encode()).hexdigest()[:16]
    a.log.parent.mkdir(parents=True, exist_ok=True)
    log = _FirstCall(BatchLog(a.log, key, evaluator, log=lambda m: print(m, flush=True), chunk=a.chunk))
    # a start's R comes from its stored features (the label's validated R_actual where a row is missing)
    start_r = np.where(np.isfinite(r_start), r_start, r_given)
    t0 = time.perf_counter()
    pol = polish(targets, theta0, start_r, feats0, scales, log, a.budget, a.popsize, a.sigma0, a.below, seed=a.seed)
    wall = time.perf_counter() - t0
    improved = pol.r_actual > start_r + 1e-12
    final = np.where(improved, pol.r_actual, r_given)  # an unimproved target keeps its validated start
    resim = pol.polished & ~np.all(np.isfinite(feats0), axis=1)
    start_resim = None
    if resim.any() and log.first is not None and len(log.first) == int(resim.sum()):
        r_re = recovery_reward(np.nan_to_num(log.first), targets[resim], scales)
        r_re = np.where(np.all(np.isfinite(log.first), axis=1), r_re, np.nan)
        dif = r_re - r_given[resim]
        start_resim = {"n": int(resim.sum()), "r_resimulated_mean": float(np.nanmean(r_re)),
                       "r_validated_mean": float(r_given[resim].mean()), "diff_mean": float(np.nanmean(dif)),
                       "abs_diff_median": float(np.nanmedian(np.abs(dif))), "abs_diff_max": float(np.nanmax(np.abs(dif))),
                       "failed": int(np.isnan(r_re).sum())}

    sets = np.array(["farthest_point" if i < len(tg["features"]) // 2 else "random" for i in range(n)])
    sel = tg.get("selection", "")

    out = {
        "benchmark": "bench_polish_from_lookup",
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
        "device": pol.device or getattr(evaluator, "device", ""),
        "simulator": inv.bundle.manifest["simulator"]["name"],
        "simulator_version": inv.bundle.manifest["simulator"]["version"],
        "config_hash": RunIdentity.of(sim).config,
        "simulator_config": {**inv.bundle.manifest["simulator"]["config"], **overrides},
        "report": str(a.report), "start": a.start, "bundle": str(a.bundle), "selection": sel, "targets": n,
        "settings": settings,
        "starts_from_stored_rows": int(np.all(np.isfinite(feats0), axis=1).sum()),
        "start_r_stored_vs_validated_max_abs": float(np.nanmax(np.abs(r_start - r_given)))
        if np.isfinite(r_start).any() else None,
        "start_resimulated": start_resim,
        "polished": int(pol.polished.sum()),
        "improved": int(improved.sum()),
        "runs": {"total": int(pol.runs.sum()), "per_target_mean": float(pol.runs.mean()),
                 "per_polished_target": float(pol.runs[pol.polished].mean()) if pol.polished.any() else 0.0,
                 "replayed": pol.replayed_runs},
        "simulator_seconds": pol.seconds, "wall_s_this_call": wall,
        "gpu_seconds_per_polished_target": pol.seconds / max(int(pol.polished.sum()), 1),
        # "lookup": the nearest-neighbour baseline; "start": the --start label's validated answers
        "r_actual": {"lookup": mean_with_ci(r_lookup), "start": mean_with_ci(r_given), "start_then_polish": mean_with_ci(final)},
        "vs_lookup": paired_difference(final, r_lookup),
        "vs_start": paired_difference(final, r_given),
        "polished_targets": {"before": mean_with_ci(r_given[pol.polished]), "after": mean_with_ci(final[pol.polished])},
        "by_set": {s: {"lookup": float(r_lookup[sets == s].mean()), "start": float(r_given[sets == s].mean()),
                       "polished": float(final[sets == s].mean())}
                   for s in ("farthest_point", "random") if (sets == s).any()},
        "per_target": [{"index": i, "lookup": float(r_lookup[i]), "start": float(r_given[i]), "final": float(final[i]),
                        "runs": int(pol.runs[i]), "polished": bool(pol.polished[i]),
                        "theta": space.denormalize(pol.theta[i:i + 1])[0].tolist()} for i in range(n)],
    }
    if a.recheck > 0:
        out["recheck"] = _recheck(a.recheck, evaluator, pol.theta[:n], targets, scales, final, r_lookup,
                                  a.out.with_suffix(".recheck.npz"))
    if a.compare is not None:
        other = json.loads(a.compare.read_text())
        if np.allclose(np.asarray(other["targets"]["features"])[:n], targets):
            labels = sorted({r["optimizer"] for r in other["rows"]})
            comp = {}
            for lab in labels:
                rr = {r["target_index"]: r["r_actual"] for r in other["rows"] if r["optimizer"] == lab}
                if len(rr) >= n:
                    v = np.array([rr[i] for i in range(n)], dtype=np.float64)
                    comp[lab] = {**mean_with_ci(v), "polished_minus_this": paired_difference(final, v)}
            out["compare"] = {"report": str(a.compare), "labels": comp}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(out, indent=1) + "\n")
    m = out["r_actual"]
    print(f"{a.start} {m['start']['mean']:.4f} -> polished {m['start_then_polish']['mean']:.4f} "
          f"{m['start_then_polish']['ci95']}; vs lookup {out['vs_lookup']['mean_diff']:+.4f} "
          f"{out['vs_lookup']['ci95']}; {out['polished']} polished, {out['improved']} improved, "
          f"{out['runs']['total']} runs ({pol.replayed_runs} replayed), {pol.seconds:.0f} simulator-s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
