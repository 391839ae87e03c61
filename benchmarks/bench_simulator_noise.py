"""Re-simulation noise of a stored orange-peel dataset: re-run stored rows, compare with stored features.

    python benchmarks/bench_simulator_noise.py datasets/orange_peel_paper --rows 64 --arch cuda \\
        --out benchmarks/results/simulator_noise_paper.json

Picks ``--rows`` ok rows (seeded), re-simulates them with the dataset's simulator settings (preset,
backend and the stored config; ``--arch`` and ``--batch`` only choose the device), extracts features
and reports, per row, R_gt = exp(-3 rms_k((y_k - y*_k) / s_k)) with s_k = p95 - p5 of the dataset's
features (the paper's recovery reward with the stored features as target), and per feature the
noise ceiling on R^2: 1 - var(y_again - y_stored) / (2 var(y)) (two independent noisy draws).

``--jitter DELTA --repeats K`` also re-simulates each picked row at K points moved by DELTA (normalised
units, a random direction of length DELTA, clipped to the box) and reports, per feature, the *roughness
ceiling* on R^2: ``1 - mean_rows var_within / var(y)``, the variance among a row's K + 1 nearby runs (its exact
re-run included) against the dataset's. For a smooth simulator and a small DELTA it is ~1; a low value means
the feature changes erratically under tiny parameter changes, which no surrogate trained on 2,000 rows can
learn (unlike the exact re-run, this sees chaos in the time-step sequence and the fracture pattern).

``--config JSON`` re-runs the rows with other simulator settings (e.g. ``'{"eta_dt_factor": 1000}'``: no
damage-resolved time step): a what-if, not a noise measurement. R_gt then measures how far those settings move
the features from the stored ones, to be read against a plain re-run's (the noise); the JSON records the
settings (``what_if``) and the seconds per run, and the config-hash check is skipped (simulator, preset,
backend and version must still match).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--rows", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arch", default="cuda", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--jitter", type=float, default=0.0, help="also re-run each row this far away (normalised)")
    ap.add_argument("--repeats", type=int, default=4, help="jittered points per row (with --jitter)")
    ap.add_argument("--warmup", type=int, default=0, help="simulate this many picked rows first, untimed (compile)")
    ap.add_argument("--config", type=json.loads, default=None,
                    help="JSON object of simulator settings to change (a what-if against the stored features)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)

    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import DatasetStore
    from invphys.core.objectives import percentile_scales, recovery_reward

    store = DatasetStore(args.dataset)
    data = store.arrays(ok_only=True)
    meta = store.metadata
    ident = meta["identity"]
    rng = np.random.default_rng(args.seed)
    pick = np.sort(rng.choice(len(data.theta), size=min(args.rows, len(data.theta)), replace=False))
    what_if = args.config or {}
    if not isinstance(what_if, dict) or {"preset", "backend", "arch", "batch_size"} & set(what_if):
        raise SystemExit("--config: a JSON object of settings other than preset, backend, arch and batch_size")
    sim = OrangePeelSimulator(preset=ident["preset"], backend=ident["backend"], arch=args.arch,
                              batch_size=args.batch, **what_if)
    from invphys.core.dataset import RunIdentity

    mine = RunIdentity.of(sim).to_dict()
    if any(mine.get(k) != v for k, v in ident.items() if not (what_if and k == "config")):
        raise SystemExit(f"dataset made by simulator {ident}, this is {mine}")
    space = sim.parameter_space()
    jittered = jitter_points(data.theta[pick], args.jitter, args.repeats, rng) if args.jitter > 0 else None
    points = data.params[pick] if jittered is None else \
        np.concatenate([data.params[pick], space.denormalize(jittered.reshape(-1, space.dim))])
    if args.warmup:
        sim.simulate(points[:args.warmup])
    t0 = time.perf_counter()
    results = sim.simulate(points)
    wall = time.perf_counter() - t0
    ex = OrangePeelFeatures()
    feats = np.array([ex.extract(r.trajectory) if r.ok else np.full(len(ex.feature_names), np.nan)
                      for r in results])
    ok = np.array([r.ok for r in results[:len(pick)]])
    again = feats[:len(pick)]
    stored = data.y[pick]
    scales = percentile_scales(data.y)
    r_gt = recovery_reward(again[ok], stored[ok], scales)
    diff = again[ok] - stored[ok]
    var_y = data.y.var(axis=0)
    ceiling = 1.0 - diff.var(axis=0) / (2.0 * np.maximum(var_y, 1e-300))
    out = {
        "benchmark": "bench_simulator_noise",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_simulator_noise.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "dataset": str(args.dataset), "identity": ident, "simulator_version": sim.version,
        "device": results[0].stats.device, "rows": len(pick), "rerun_ok": int(ok.sum()),
        "wall_s": wall, "wall_per_run_s": wall / len(points), "what_if": what_if or None,
        "substeps_per_run": float(np.mean([r.stats.substeps for r in results[:len(pick)]])),
        "r_gt": {"median": float(np.median(r_gt)), "mean": float(r_gt.mean()), "min": float(r_gt.min()),
                 "p10": float(np.percentile(r_gt, 10)), "below_0.95": int((r_gt < 0.95).sum())},
        "r2_noise_ceiling": dict(zip(ex.feature_names, ceiling.round(6).tolist(), strict=True)),
        "r2_noise_ceiling_mean": float(ceiling.mean()),
        "max_abs_diff_over_scale": dict(zip(ex.feature_names, (np.abs(diff).max(0) / scales).round(6).tolist(),
                                            strict=True)),
    }
    if jittered is not None:
        groups = np.concatenate([again[:, None], feats[len(pick):].reshape(len(pick), args.repeats, -1)], axis=1)
        full = np.isfinite(groups).all(axis=(1, 2))
        within = groups[full].var(axis=1, ddof=1).mean(axis=0)
        rough = 1.0 - within / np.maximum(var_y, 1e-300)
        out["jitter"] = {"delta": args.jitter, "repeats": args.repeats, "rows_complete": int(full.sum()),
                         "runs": len(points),
                         "r2_roughness_ceiling": dict(zip(ex.feature_names, rough.round(6).tolist(), strict=True)),
                         "r2_roughness_ceiling_mean": float(rough.mean())}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    print(json.dumps({k: out[k] for k in ("device", "rows", "rerun_ok", "wall_s", "wall_per_run_s", "what_if",
                                          "substeps_per_run", "r_gt",
                                          "r2_noise_ceiling_mean", "jitter") if k in out}, indent=2))
    return out


def jitter_points(theta: np.ndarray, delta: float, repeats: int, rng: np.random.Generator) -> np.ndarray:
    """(rows, repeats, dim) normalised points at distance ``delta`` from each row (random directions),
    clipped to the unit box."""
    u = rng.normal(size=(len(theta), repeats, theta.shape[1]))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    return np.clip(theta[:, None, :] + delta * u, 0.0, 1.0)


if __name__ == "__main__":
    main()
