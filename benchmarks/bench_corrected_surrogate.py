"""Does correcting the surrogate by the residuals of the nearest stored rows predict held-out features better?

    python benchmarks/bench_corrected_surrogate.py --bundle inverters/orange_peel_paper_all \\
        --sets test=@test uniform=datasets/orange_peel_paper_fresh_uniform \\
               edge=datasets/orange_peel_paper_fresh_edge faces=datasets/orange_peel_paper_faces \\
        --k 8 16 32 --bandwidth 0.03 0.05 0.08 0.12 --out runs/corrected_surrogate.json

For every held-out row (parameters and simulated features known, never trained on) the plain ensemble
mean ``f(theta)`` is compared with the corrected prediction
``f(theta) + sum_j w_j r_j / (prior + sum_j w_j)``, r_j = y_j - f(theta_j) the residuals of the ``k``
training rows nearest ``theta`` in normalised parameter space, w_j = exp(-d_j^2 / (2 h^2)) (``h`` the
bandwidth; ``prior`` the weight of "no correction", so a far-away row barely moves the prediction).
``units=log`` corrects positive features multiplicatively (residuals of log|y|). Per set: the mean
recovery of the prediction against the row's real features (``masked_recovery`` with the bundle's scales,
the R an answer would get if the prediction were right) and the mean R^2 over features (scaled).
``@test`` is the bundle's own held-out partition.

``--rule-sets`` measures the pool's ``exact`` rule with real features only: the stored rows (training and
held-out) are split at random in halves A and B; A plays the surrogate-scored candidates (the pick: best
``R_surr - lam x std``), B the stored rows scored exactly; the hybrid keeps B's best unless A's pick scores
more than ``margin`` above it. Every choice is a stored row, so its real R is known: mean real R per rule
(averaged over ``--splits`` random halvings), and the surrogate's optimism at A's pick.

``--probe N`` (needs the bundle's simulator: a GPU for the paper preset) measures what the stored rows
cannot: how the surrogate's error varies over SHORT distances. Around each of the first N held-out rows
(``data/test.npz``) it simulates ``--probe-dirs`` points at each ``--probe-distances`` (normalised
units, random directions; distance 0: the row re-run) and reports per distance: R of the new run
against the row's own features (how fast a stored row's match decays), the surrogate's recovery of the
new run plain and anchored (``f(theta') + y_j - f(theta_j)``: the row's residual carried over) and the
correlation of the two residuals. An anchored correction helps only where that correlation is above 1/2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def _rows(inv: Any, spec: str) -> tuple[np.ndarray, np.ndarray]:
    if spec == "@test":
        return inv.bundle.data("test")
    from invphys.core.dataset import DatasetStore

    a = DatasetStore(spec).arrays(ok_only=True)
    return np.asarray(a.theta, dtype=np.float64), np.asarray(a.y, dtype=np.float64)


def correction(theta: np.ndarray, train_theta: np.ndarray, resid: np.ndarray, k: int, h: float,
               prior: float) -> np.ndarray:
    """(N, M) kernel-weighted mean residual of the k nearest training rows of each theta."""
    d2 = (theta * theta).sum(1)[:, None] + (train_theta * train_theta).sum(1)[None, :] - 2 * theta @ train_theta.T
    d2 = np.maximum(d2, 0.0)
    idx = np.argpartition(d2, k - 1, axis=1)[:, :k]
    dk = np.take_along_axis(d2, idx, axis=1)
    w = np.exp(-dk / (2 * h * h))
    return np.einsum("nk,nkm->nm", w, resid[idx]) / (prior + w.sum(1))[:, None]


def _metrics(pred: np.ndarray, y: np.ndarray, scales: np.ndarray, kappa: float) -> dict[str, float]:
    from invphys.core.masked_recovery import masked_recovery

    ok = np.all(np.isfinite(y), axis=1)
    p, t = pred[ok], y[ok]
    r = masked_recovery(p, t, scales, np.ones(y.shape[1], dtype=bool), kappa)
    r2 = 1 - ((p - t) ** 2).sum(0) / np.maximum(((t - t.mean(0)) ** 2).sum(0), 1e-300)
    return {"recovery_mean": float(r.mean()), "recovery_median": float(np.median(r)),
            "r2_mean": float(r2.mean()), "rmse_scaled": float(np.sqrt((((p - t) / scales) ** 2).mean()))}


def hybrid_rule(inv: Any, y_targets: np.ndarray, margins: list[float], splits: int, lam: float
                ) -> dict[str, float]:
    """Mean real R of: the surrogate's pick among half A of the stored rows, the exact lookup over half B,
    their better one (oracle) and the hybrid per margin (module docstring)."""
    from invphys.core.masked_recovery import masked_recovery
    from invphys.evaluators.uncertainty import normalised_std

    b = inv.bundle
    parts = [b.data("train"), b.data("test")]
    theta, y = np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
    ok = np.all(np.isfinite(y), axis=1)
    theta, y = theta[ok], y[ok]
    mean, std = b.surrogate.predict_with_uncertainty(theta)
    pen = lam * normalised_std(std, b.scales)
    rs = np.stack([masked_recovery(mean, t, b.scales, None, b.kappa) for t in y_targets])
    re = np.stack([masked_recovery(y, t, b.scales, None, b.kappa) for t in y_targets])
    n, rows = len(y_targets), np.arange(len(y_targets))
    acc: dict[str, list[float]] = {}
    for split in range(splits):
        in_a = np.random.default_rng(split).random(len(y)) < 0.5
        score = np.where(in_a[None], rs - pen[None], -np.inf)
        ja = score.argmax(1)
        jb = np.where(~in_a[None], re, -np.inf).argmax(1)
        ra, rb, sa = re[rows, ja], re[rows, jb], score[rows, ja]
        for key, v in (("surrogate_pick_A", ra), ("optimism_at_A_pick", rs[rows, ja] - ra),
                       ("exact_lookup_B", rb), ("oracle_max", np.maximum(ra, rb))):
            acc.setdefault(key, []).append(float(v.mean()))
        for m in margins:
            acc.setdefault(f"hybrid_margin_{m:g}", []).append(float(np.where(sa - m > rb, ra, rb).mean()))
    return {k: float(np.mean(v)) for k, v in acc.items()} | {"targets": n, "stored_rows": len(y)}


def probe(inv: Any, rows: int, distances: list[float], dirs: int, overrides: dict[str, str], batch: int
          ) -> dict[str, Any]:
    """Simulate points at short distances from held-out stored rows (module docstring)."""
    from invphys.core.masked_recovery import masked_recovery

    b = inv.bundle
    theta, y = b.data("test")
    ok = np.flatnonzero(np.all(np.isfinite(y), axis=1))[:rows]
    theta, y = theta[ok], y[ok]
    u = np.random.default_rng(0).normal(size=(len(theta), dirs, theta.shape[1]))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    plan = [(i, d, np.clip(theta[i] + d * u[i, k], 0.0, 1.0)) for d in distances for i in range(len(theta))
            for k in range(dirs)]
    results = [inv.evaluate(theta=t, target=y[i], label=f"probe {d:g}") for i, d, t in plan]
    t0 = time.perf_counter()
    inv.validate(results, overrides=overrides, batch_size=batch)
    anchor = y - b.surrogate.predict(theta)
    out: dict[str, Any] = {"rows": len(theta), "dirs": dirs, "runs": len(plan),
                           "simulate_s": time.perf_counter() - t0, "by_distance": {}}
    for d in distances:
        idx = [n for n, (_, dd, _) in enumerate(plan) if dd == d and results[n].candidates[0].actual is not None]
        if not idx:
            continue
        sim = np.array([results[n].candidates[0].actual for n in idx], dtype=np.float64)
        pred = np.array([results[n].candidates[0].predicted for n in idx], dtype=np.float64)
        rows_i = np.array([plan[n][0] for n in idx])
        good = np.all(np.isfinite(sim), axis=1)
        sim, pred, rows_i = sim[good], pred[good], rows_i[good]
        e_new, e_row = (sim - pred) / b.scales, anchor[rows_i] / b.scales
        out["by_distance"][f"{d:g}"] = {
            "runs": len(sim),
            "r_new_run_vs_row": float(masked_recovery(sim, y[rows_i], b.scales, None, b.kappa).mean()),
            "r_surrogate_plain": float(masked_recovery(pred, sim, b.scales, None, b.kappa).mean()),
            "r_surrogate_anchored": float(masked_recovery(pred + anchor[rows_i], sim, b.scales, None, b.kappa).mean()),
            "residual_corr": float(np.corrcoef(e_new.ravel(), e_row.ravel())[0, 1]) if len(sim) > 1 else None}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--bundle", required=True)
    p.add_argument("--sets", nargs="*", default=[], help="NAME=STORE or NAME=@test")
    p.add_argument("--k", nargs="+", type=int, default=[8, 16, 32])
    p.add_argument("--bandwidth", nargs="+", type=float, default=[0.03, 0.05, 0.08, 0.12])
    p.add_argument("--prior", nargs="+", type=float, default=[0.0, 0.5, 1.0])
    p.add_argument("--units", nargs="+", default=["raw", "log"])
    p.add_argument("--rule-sets", nargs="*", default=[], help="NAME=STORE: targets for the exact-rule check")
    p.add_argument("--margins", nargs="+", type=float, default=[0.0, 0.02, 0.03, 0.05, 0.07, 0.1])
    p.add_argument("--splits", type=int, default=6)
    p.add_argument("--lam", type=float, default=0.5)
    p.add_argument("--probe", type=int, default=0, help="held-out rows to probe on the simulator (GPU)")
    p.add_argument("--probe-distances", nargs="+", type=float, default=[0.0, 0.01, 0.03, 0.06, 0.1])
    p.add_argument("--probe-dirs", type=int, default=4)
    p.add_argument("--sim-option", nargs="*", default=[], help="KEY=VALUE simulator overrides (e.g. arch=cpu)")
    p.add_argument("--sim-batch", type=int, default=64)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)

    from invphys.inverter import load_inverter

    inv = load_inverter(a.bundle)
    b = inv.bundle
    tt, ty = b.data("train")
    ok = np.all(np.isfinite(ty), axis=1)
    tt, ty = tt[ok], ty[ok]
    t0 = time.perf_counter()
    ft = b.surrogate.predict(tt)
    pos = np.all(ty > 0, axis=0)  # features whose log is defined on every training row
    resid = {"raw": ty - ft, "log": np.where(pos, np.log(np.where(pos, ty, 1.0)) - np.log(np.abs(np.where(pos, ft, 1.0))
                                                                                      + 1e-300), ty - ft)}
    print(f"training residuals in {time.perf_counter() - t0:.1f} s; log-units features: {int(pos.sum())}",
          file=sys.stderr)
    if str(Path(__file__).parent) not in sys.path:
        sys.path.insert(0, str(Path(__file__).parent))
    import _machine

    out: dict[str, Any] = {"benchmark": "corrected_surrogate", **_machine.provenance(),
                           "device": f"cpu ({_machine.cpu_name()})", "bundle": a.bundle, "train_rows": len(tt),
                           "train_recovery_of_surrogate": _metrics(ft, ty, b.scales, b.kappa), "sets": {}}
    for spec in a.sets:
        name, _, path = spec.partition("=")
        theta, y = _rows(inv, path)
        f = b.surrogate.predict(theta)
        rows: dict[str, Any] = {"plain": _metrics(f, y, b.scales, b.kappa)}
        for units in a.units:
            for k in a.k:
                for h in a.bandwidth:
                    for prior in a.prior:
                        c = correction(theta, tt, resid[units], k, h, prior)
                        if units == "log":
                            pred = np.where(pos, np.sign(f) * np.exp(np.log(np.abs(f) + 1e-300) + c), f + c)
                            pred = np.where(pos & (f <= 0), f, pred)
                        else:
                            pred = f + c
                        rows[f"{units} k={k} h={h} prior={prior}"] = _metrics(pred, y, b.scales, b.kappa)
        best = max((v["recovery_mean"], m) for m, v in rows.items())
        print(f"{name:8s} n={len(y):5d} plain R {rows['plain']['recovery_mean']:.4f} R2 {rows['plain']['r2_mean']:.4f}"
              f" | best {best[1]}: R {best[0]:.4f} R2 {rows[best[1]]['r2_mean']:.4f}", file=sys.stderr)
        out["sets"][name] = {"store": path, "n": len(y), "variants": rows}
    out["exact_rule"] = {}
    for spec in a.rule_sets:
        name, _, path = spec.partition("=")
        row = hybrid_rule(inv, _rows(inv, path)[1], a.margins, a.splits, a.lam)
        out["exact_rule"][name] = {"store": path, **row}
        print(f"{name:8s} rule: " + ", ".join(f"{k} {v:.4f}" for k, v in row.items() if isinstance(v, float)),
              file=sys.stderr)
    if a.probe:
        out["probe"] = probe(inv, a.probe, a.probe_distances, a.probe_dirs,
                             dict(kv.split("=", 1) for kv in a.sim_option), a.sim_batch)
        for d, row in out["probe"]["by_distance"].items():
            print(f"probe d={d}: " + ", ".join(f"{k} {v:.4f}" for k, v in row.items() if isinstance(v, float)),
                  file=sys.stderr)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
