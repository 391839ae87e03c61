"""Benchmark the learned models: accuracy against the paper, single-call latency, batched throughput.

Usage::

    .venv/bin/python benchmarks/bench_surrogate.py                 # CPU, writes benchmarks/results/surrogate_cpu.json
    .venv/bin/python benchmarks/bench_surrogate.py --device cuda   # writes surrogate_cuda.json
    .venv/bin/python benchmarks/bench_surrogate.py --quick         # fewer epochs and repeats (smoke test)

Data: ``tests/data/orange_tiny.npz`` (or ``--data`` with the same keys), split 80/20 with a seed.
Models use their paper defaults (MLP: Adam 1e-3, weight decay 1e-4, early stopping patience 50;
latent models: 4-D, beta/alpha 0.1 with a 50-epoch warm-up, gamma 1). Accuracy is measured on the
held-out 20 %, which is also the early-stopping set (the paper's protocol).

Latency is the median wall time of ``predict`` on one row (the call an optimiser makes per
evaluation), after warm-up, including the NumPy <-> torch conversion; ``forward_us`` is the bare
network call on a ready tensor. Throughput is rows per second of ``predict`` on batches.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
PAPER = {"mlp_r2": 0.937, "mlp_r2_per_feature_range": [0.854, 0.991], "latency_ms": [0.1, 0.13],
         "vae_recon_mse": 0.007, "vae_head_r2": 0.854, "flow_recon_mse": 0.059, "flow_head_r2": 0.913,
         "n_runs": 2000, "preset": "paper (AnisoMPM, ~50k particles)"}


def _split(data: dict, seed: int) -> tuple[np.ndarray, ...]:
    n = len(data["theta"])
    perm = np.random.default_rng(seed).permutation(n)
    n_test = round(0.2 * n)
    te, tr = np.sort(perm[:n_test]), np.sort(perm[n_test:])
    return data["theta"][tr], data["y"][tr], data["theta"][te], data["y"][te]


def _latency(fn, x: np.ndarray, repeats: int) -> float:
    for _ in range(min(200, repeats)):
        fn(x)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn(x)
        times.append(time.perf_counter_ns() - t0)
    return statistics.median(times) / 1e3  # microseconds


def _throughput(fn, theta: np.ndarray, batch: int, min_time: float) -> float:
    rng = np.random.default_rng(0)
    x = theta[rng.integers(0, len(theta), size=batch)]
    fn(x)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < min_time:
        fn(x)
        n += batch
    return n / (time.perf_counter() - t0)


def _speed(model, theta: np.ndarray, repeats: int, min_time: float, batches: list[int]) -> dict:
    import torch

    x1 = theta[:1]
    out: dict = {}
    for threads in (1, torch.get_num_threads()):
        torch.set_num_threads(threads)
        t1 = torch.as_tensor(x1, dtype=torch.float32, device=model.device)
        fwd = model._folded_net()

        def bare(_x, fwd=fwd, t1=t1):
            with torch.inference_mode():
                fwd(t1)
                if t1.is_cuda:
                    torch.cuda.synchronize()

        out[f"threads_{threads}"] = {
            "latency_us": _latency(model.predict, x1, repeats),
            "forward_us": _latency(bare, x1, repeats),
            "throughput_rows_per_s": {str(b): _throughput(model.predict, theta, b, min_time) for b in batches},
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "tests" / "data" / "orange_tiny.npz"))
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="few epochs and repeats: a smoke test")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/surrogate_<device>.json)")
    args = ap.parse_args()

    import torch

    from invphys.plugins.latents.realnvp import RealNVPLatent
    from invphys.plugins.latents.vae import VAELatent
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    with np.load(args.data, allow_pickle=False) as d:
        data = {k: d[k] for k in d.files}
    tt, yt, tv, yv = _split(data, args.seed)
    names = [str(n) for n in data["feature_names"]]
    quick = {"max_epochs": 30} if args.quick else {}
    repeats, min_time = (200, 0.2) if args.quick else (3000, 1.0)
    batches = [1, 64, 1024, 16384]
    result: dict = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "torch": torch.__version__, "torch_threads_default": torch.get_num_threads(),
                    "device": args.device,
                    "gpu": torch.cuda.get_device_name(0) if args.device == "cuda" else None},
        "data": {"path": str(Path(args.data).resolve().relative_to(ROOT)) if ROOT in Path(args.data).resolve().parents
                 else args.data, "n_train": len(tt), "n_test": len(tv), "feature_names": names},
        "paper": PAPER, "models": {},
    }
    if "provenance" in data:
        result["data"]["provenance"] = json.loads(str(data["provenance"]))
    for label, model in (("mlp", MLPSurrogate(device=args.device, seed=args.seed, **quick)),
                         ("ensemble", EnsembleSurrogate(device=args.device, seed=args.seed, **quick))):
        metrics = model.fit(tt, yt, validation=(tv, yv))
        print(f"{label}: held-out R^2 {metrics['r2']:.4f} after {metrics['epochs']} epochs "
              f"({metrics['train_time_s']:.1f} s)", flush=True)
        result["models"][label] = {"config": model.config.model_dump(mode="json"), "metrics": metrics,
                                   "r2_per_feature": dict(zip(names, metrics["r2_per_feature"], strict=True)),
                                   "speed": _speed(model, tt, repeats, min_time, batches)}
        sp = result["models"][label]["speed"]["threads_1"]
        print(f"  latency {sp['latency_us']:.1f} us (forward {sp['forward_us']:.1f} us), "
              f"throughput @16384 {sp['throughput_rows_per_s']['16384']:.3g} rows/s", flush=True)
    for label, model in (("vae", VAELatent(device=args.device, seed=args.seed, **quick)),
                         ("realnvp", RealNVPLatent(device=args.device, seed=args.seed, **quick))):
        metrics = model.fit(tt, yt, validation=(tv, yv))
        print(f"{label}: recon MSE {metrics['recon_mse']:.4f}, head R^2 {metrics['head_r2']:.4f} after "
              f"{metrics['epochs']} epochs ({metrics['train_time_s']:.1f} s)", flush=True)
        z = model.encode(tv[:1])
        result["models"][label] = {
            "config": model.config.model_dump(mode="json"), "metrics": metrics,
            "decode_latency_us": _latency(model.decode, z, repeats),
            "encode_latency_us": _latency(model.encode, tv[:1], repeats)}
    # learning curve: the MLP's held-out R^2 against the number of training rows (same held-out set)
    curve = []
    sizes = [50, 100, 200, len(tt)] if not args.quick else [50, len(tt)]
    for n in sizes:
        r2s = []
        for rep in range(3 if not args.quick else 1):
            idx = np.random.default_rng(100 + rep).permutation(len(tt))[:n]
            m = MLPSurrogate(device=args.device, seed=rep, **quick)
            r2s.append(m.fit(tt[idx], yt[idx], validation=(tv, yv))["r2"])
        curve.append({"n_train": n, "r2_mean": float(np.mean(r2s)), "r2_runs": r2s})
        print(f"learning curve: {n} rows -> R^2 {np.mean(r2s):.4f}", flush=True)
    result["learning_curve_mlp"] = curve
    out = Path(args.out) if args.out else ROOT / "benchmarks" / "results" / f"surrogate_{args.device}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
