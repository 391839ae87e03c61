"""Identifiability of the orange peel's 9 parameters from its 12 features: sensitivities and rank.

    python benchmarks/bench_identifiability.py --preset quick --arch cuda --points 16 \\
        --scales-from datasets/orange_peel_quick --out benchmarks/results/identifiability_quick.json
    python benchmarks/bench_identifiability.py --preset tiny --arch cpu --points 4   # CPU, deterministic
    python benchmarks/bench_identifiability.py --surrogate inverters/orange_peel_quick --points 256 \\
        --scales-from datasets/orange_peel_quick --out benchmarks/results/identifiability_quick_surrogate.json

At ``--points`` base points drawn uniformly in [h, 1 - h]^9 (normalised space, seeded), central finite
differences with step ``--step`` (h) give the Jacobian J (12 x 9) of the features, each feature divided by
its spread s_k (p95 - p5 of ``--scales-from``'s stored features, else of the base points' features):
J[k, j] = (y_k(theta + h e_j) - y_k(theta - h e_j)) / (2 h s_k), i.e. the change of feature k, in
units of its spread, per full range of parameter j. Reported: per parameter the median column norm
|J[:, j]| (its sensitivity), the largest |cosine| between two parameters' columns (1 = the features cannot
tell the two apart locally), and the singular values of J (numerical rank at 1e-2 and 1e-3 of the largest).

``--surrogate BUNDLE`` (an inverter bundle directory) runs no simulator: the same base points and stencil
are evaluated on the bundle's fitted ensemble surrogate (its NumPy predictor, the members' mean) and go
through the same ``jacobians``/``summarise``. It measures the sensitivity of the fitted surrogate, i.e.
what the data taught it about the parameters: smooth and cheap (many points on a CPU), but only as good
as the surrogate's R^2, which is recorded (``surrogate_test_r2``, on the bundle's held-out rows).
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
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)


def jacobians(y: np.ndarray, ok: np.ndarray, points: int, dim: int, h: float, scales: np.ndarray) -> list:
    """Per base point the scaled central-difference Jacobian (M, dim), or None if a run failed.

    ``y`` rows are laid out per point as [base, +e_0, -e_0, +e_1, -e_1, ...].
    """
    per = 1 + 2 * dim
    out = []
    for k in range(points):
        rows = slice(k * per, (k + 1) * per)
        if not ok[rows].all():
            out.append(None)
            continue
        yk = y[rows]
        J = (yk[1::2] - yk[2::2]).T / (2.0 * h) / scales[:, None]
        out.append(J)
    return out


def summarise(Js: list[np.ndarray], names: tuple[str, ...]) -> dict:
    """Sensitivities, pairwise column cosines and singular values over the Jacobians."""
    J = np.stack(Js)                                    # (K, M, d)
    norms = np.linalg.norm(J, axis=1)                   # (K, d)
    unit = J / np.maximum(norms[:, None, :], 1e-300)
    cos = np.abs(np.einsum("kmi,kmj->kij", unit, unit))  # (K, d, d)
    d = J.shape[2]
    off = ~np.eye(d, dtype=bool)
    med_cos = np.median(cos, axis=0)
    worst_pair = np.unravel_index(np.argmax(np.where(off, med_cos, -1)), med_cos.shape)
    sv = np.linalg.svd(J, compute_uv=False)            # (K, d)
    rel = sv / sv[:, :1]
    return {
        "points_used": len(Js),
        "sensitivity_median": dict(zip(names, np.median(norms, 0).round(5).tolist(), strict=True)),
        "sensitivity_min_over_points": dict(zip(names, norms.min(0).round(5).tolist(), strict=True)),
        "max_abs_cosine_median": {names[i]: float(np.max(med_cos[i][off[i]]).round(4)) for i in range(d)},
        "most_alike_pair": [names[worst_pair[0]], names[worst_pair[1]], float(med_cos[worst_pair].round(4))],
        "cosine_E_rho_median": float(med_cos[names.index("E"), names.index("rho")].round(4)),
        "singular_values_rel_median": np.median(rel, 0).round(6).tolist(),
        "smallest_singular_value_rel": {"median": float(np.median(rel[:, -1])), "min": float(rel[:, -1].min())},
        "numerical_rank_1e-2": np.bincount((rel > 1e-2).sum(1), minlength=d + 1).tolist(),
        "numerical_rank_1e-3": np.bincount((rel > 1e-3).sum(1), minlength=d + 1).tolist(),
        "stacked_singular_values_rel": (lambda s: (s / s[0]).round(6).tolist())(
            np.linalg.svd(J.reshape(-1, d), compute_uv=False)),
    }


def stencil(base: np.ndarray, h: float) -> np.ndarray:
    """The central-difference points per base point, laid out as [base, +e_0, -e_0, +e_1, -e_1, ...]."""
    d = base.shape[1]
    theta = []
    for b in base:
        theta.append(b)
        for j in range(d):
            for sgn in (1.0, -1.0):
                t = b.copy()
                t[j] += sgn * h
                theta.append(t)
    return np.asarray(theta)


def base_points(points: int, dim: int, h: float, seed: int) -> np.ndarray:
    """``points`` base points uniform in [h, 1 - h]^dim (normalised space), seeded."""
    return h + (1 - 2 * h) * np.random.default_rng(seed).uniform(size=(points, dim))


def surrogate_mode(args: argparse.Namespace, argv: list[str] | None) -> dict:
    """The Jacobians of the bundle's fitted surrogate at the simulator mode's points and stencil."""
    import os

    import invphys
    from benchmarks._machine import cpu_name
    from invphys.core.objectives import percentile_scales
    from invphys.inverter import BundleError
    from invphys.models.data import r2_scores

    inv = invphys.load_inverter(args.surrogate)
    bundle = inv.bundle
    manifest = bundle.manifest
    names, fnames = bundle.space.names, bundle.feature_names
    sim_info = manifest["simulator"]
    h, d = args.step, bundle.space.dim
    theta = stencil(base_points(args.points, d, h, args.seed), h)
    surrogate = bundle.surrogate
    t0 = time.perf_counter()
    y = np.asarray(surrogate.predict(theta), dtype=np.float64)
    wall = time.perf_counter() - t0
    ok = np.isfinite(y).all(axis=1)
    if args.scales_from is not None:
        from invphys.core.dataset import DatasetStore

        store = DatasetStore(args.scales_from)
        arrays = store.arrays(ok_only=True)
        if tuple(arrays.feature_names) != tuple(fnames):
            raise SystemExit(f"--scales-from {args.scales_from} holds other features than the bundle predicts "
                             f"({list(arrays.feature_names)} vs {list(fnames)})")
        scales = percentile_scales(arrays.y)
        scale_source = str(args.scales_from)
        identity = store.metadata.get("identity") or {}
        dataset = {"path": scale_source, "simulator": identity.get("simulator"), "version": identity.get("version"),
                   "preset": identity.get("preset"), "rows": len(arrays)}
    else:
        scales = percentile_scales(y[:: 1 + 2 * d][ok[:: 1 + 2 * d]])
        scale_source = "base points"
        dataset = None
    Js = [J for J in jacobians(y, ok, args.points, d, h, scales) if J is not None]
    try:
        th_test, y_test = bundle.data("test")
    except BundleError:  # a bundle shipped without its held-out rows
        r2 = None
    else:
        r2_all, r2_each = r2_scores(y_test, surrogate.predict(th_test))
        r2 = {"overall": round(float(r2_all), 4), "rows": len(y_test),
              **dict(zip(fnames, np.round(r2_each, 4).tolist(), strict=True))}
    members = surrogate.members(theta[:1]).shape[0]
    out = {
        "benchmark": "bench_identifiability",
        "mode": "surrogate",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_identifiability.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "bundle": str(args.surrogate), "bundle_id": str(manifest.get("bundle_id", "")),
        "bundle_name": manifest.get("name"),
        "surrogate": {"type": manifest["components"]["surrogate"].get("type"), "members": int(members),
                      "predictor": "Bundle.surrogate.predict (members' mean, NumPy inference form)"},
        "simulator": sim_info.get("name"), "simulator_version": sim_info.get("version"),
        "preset": (sim_info.get("config") or {}).get("preset"),
        "trained_on": manifest.get("dataset"),
        "dataset": dataset,
        "device": "cpu", "machine": {"cpu": cpu_name(), "cpu_count": os.cpu_count(),
                                     "platform": platform.platform(terse=True)},
        "points": args.points, "step": h, "seed": args.seed,
        "evaluations": len(theta), "failed": int((~ok).sum()), "wall_s": wall, "scales_from": scale_source,
        "feature_names": list(fnames), "param_names": list(names),
        "scales": scales.tolist(),
        "surrogate_test_r2": r2,
        **summarise(Js, names),
        "jacobians": [J.round(5).tolist() for J in Js],
    }
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default=None, help="simulator preset (default tiny; --surrogate: the bundle's)")
    ap.add_argument("--backend", default="taichi", choices=["taichi", "warp"])
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--points", type=int, default=4)
    ap.add_argument("--step", type=float, default=0.05, help="h, in the normalised [0, 1] space")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--scales-from", type=Path, default=None, help="a dataset whose feature spread scales J")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--surrogate", type=Path, default=None, metavar="BUNDLE",
                    help="an inverter bundle: differentiate its fitted surrogate instead of the simulator")
    args = ap.parse_args(argv)
    if args.surrogate is not None:
        out = surrogate_mode(args, argv)
        if args.preset is not None and args.preset != out["preset"]:
            raise SystemExit(f"--preset {args.preset}: the bundle {args.surrogate} was trained on the "
                             f"{out['preset']} preset (leave --preset out with --surrogate)")
        path = args.out or ROOT / "benchmarks" / "results" / f"identifiability_{out['preset']}_surrogate.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=2))
        print(json.dumps({k: v for k, v in out.items() if k != "jacobians"}, indent=2))
        return out
    args.preset = args.preset or "tiny"

    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.objectives import percentile_scales

    h = args.step
    sim = OrangePeelSimulator(preset=args.preset, backend=args.backend, arch=args.arch, batch_size=args.batch)
    space = sim.parameter_space()
    d = space.dim
    theta = stencil(base_points(args.points, d, h, args.seed), h)
    t0 = time.perf_counter()
    results = sim.simulate(space.denormalize(theta))
    wall = time.perf_counter() - t0
    ex = OrangePeelFeatures()
    ok = np.array([r.ok for r in results])
    y = np.array([ex.extract(r.trajectory) if r.ok else np.full(12, np.nan) for r in results])
    if args.scales_from is not None:
        from invphys.core.dataset import DatasetStore

        scales = percentile_scales(DatasetStore(args.scales_from).arrays(ok_only=True).y)
        scale_source = str(args.scales_from)
    else:
        scales = percentile_scales(y[:: 1 + 2 * d][ok[:: 1 + 2 * d]])
        scale_source = "base points"
    Js = [J for J in jacobians(y, ok, args.points, d, h, scales) if J is not None]
    out = {
        "benchmark": "bench_identifiability",
        "mode": "simulator",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_identifiability.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "simulator_version": sim.version, "preset": args.preset, "backend": args.backend,
        "device": results[0].stats.device, "points": args.points, "step": h, "seed": args.seed,
        "runs": len(theta), "failed": int((~ok).sum()), "wall_s": wall, "scales_from": scale_source,
        "feature_names": list(ex.feature_names), "param_names": list(space.names),
        "scales": scales.tolist(),
        **summarise(Js, space.names),
        "jacobians": [J.round(5).tolist() for J in Js],
    }
    path = args.out or ROOT / "benchmarks" / "results" / f"identifiability_{args.preset}_{args.arch}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(json.dumps({k: v for k, v in out.items() if k != "jacobians"}, indent=2))
    return out


if __name__ == "__main__":
    main()
