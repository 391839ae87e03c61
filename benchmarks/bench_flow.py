"""The RealNVP latent model's flow: our direct coupling evaluation against zuko's own transforms.

Usage::

    .venv/bin/python benchmarks/bench_flow.py            # writes benchmarks/results/flow_eval_cpu.json
    .venv/bin/python benchmarks/bench_flow.py --quick    # fewer epochs and repeats (smoke test)

Both paths use the same zuko ``GeneralCouplingTransform`` modules and weights
(:class:`invphys.models.nets.FlowNet`, ``evaluation = "direct" | "zuko"``). For each path: a full
``RealNVPLatent.fit`` at the paper's settings (fixed epochs, no early stop) on
``tests/data/orange_tiny.npz``, then the median latency of ``decode`` on one row (what a latent-space
optimiser calls per evaluation) and of ``encode`` on 256 rows; plus the largest difference between the
two paths' outputs on the same trained weights. Times are CPU (process) time on one torch thread, so
that other processes on a shared machine do not count; the paths alternate over ``--rounds`` rounds and
each number is the best round. ``fit_wall_s`` is the wall time, for reference.
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


def _median_us(fn, x: np.ndarray, repeats: int) -> float:
    """Median CPU time of ``fn(x)`` in microseconds (process time: what other processes do not inflate)."""
    for _ in range(min(100, repeats)):
        fn(x)
    times = []
    for _ in range(repeats):
        t0 = time.process_time_ns()
        fn(x)
        times.append(time.process_time_ns() - t0)
    return statistics.median(times) / 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=1000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "flow_eval_cpu.json"))
    args = ap.parse_args()
    if args.quick:
        args.epochs, args.repeats, args.rounds = 10, 200, 1

    import torch
    import zuko

    from invphys.models.nets import FlowNet
    from invphys.plugins.latents.realnvp import RealNVPLatent

    data = dict(np.load(ROOT / "tests" / "data" / "orange_tiny.npz", allow_pickle=False))
    n = len(data["theta"])
    perm = np.random.default_rng(0).permutation(n)
    te, tr = np.sort(perm[: n // 5]), np.sort(perm[n // 5:])
    theta, y, tv, yv = data["theta"][tr], data["y"][tr], data["theta"][te], data["y"][te]
    result: dict = {
        "command": " ".join(["python", *sys.argv]),
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "python": platform.python_version(), "torch": torch.__version__, "zuko": zuko.__version__,
                    "device": "cpu", "torch_threads": 1, "timer": "process CPU time",
                    "cpus": __import__("os").cpu_count(), "load_average_at_start": __import__("os").getloadavg()},
        "data": {"file": "tests/data/orange_tiny.npz", "n_train": len(tr), "n_val": len(te)},
        "epochs": args.epochs, "rounds": args.rounds, "paths": {}}
    models: dict = {}
    rounds: dict[str, list[dict]] = {"direct": [], "zuko": []}
    for r in range(args.rounds):
        for path in (("direct", "zuko") if r % 2 == 0 else ("zuko", "direct")):
            FlowNet.evaluation = path
            model = RealNVPLatent(max_epochs=args.epochs, patience=10 * args.epochs, seed=0, threads=1)
            t0, c0 = time.perf_counter(), time.process_time()
            metrics = model.fit(theta, y, validation=(tv, yv))
            fit_s, fit_wall = time.process_time() - c0, time.perf_counter() - t0
            one = np.full((1, model.latent_dim), 0.1)
            batch = tv[np.random.default_rng(1).integers(0, len(tv), size=256)]
            rounds[path].append({
                "ms_per_epoch": 1e3 * fit_s / metrics["epochs"], "fit_wall_s": fit_wall,
                "decode_1row_us": _median_us(model.decode, one, args.repeats),
                "encode_256rows_us": _median_us(model.encode, batch, max(50, args.repeats // 10)),
                "recon_mse": metrics["recon_mse"], "head_r2": metrics["head_r2"]})
            models[path] = model
            print(r, path, rounds[path][-1], flush=True)
    for path, rows in rounds.items():
        result["paths"][path] = {k: round(min(row[k] for row in rows), 3)
                                 for k in ("ms_per_epoch", "decode_1row_us", "encode_256rows_us")}
        result["paths"][path] |= {"recon_mse": rows[-1]["recon_mse"], "head_r2": rows[-1]["head_r2"],
                                  "rounds": rows}
    # the same weights evaluated both ways
    net = models["direct"]._net
    with torch.no_grad():
        h = net.proj_in(torch.as_tensor(tv, dtype=torch.float32))
        FlowNet.evaluation = "direct"
        z_d, l_d = net.flow_forward(h)
        back_d = net.flow_inverse(z_d)
        FlowNet.evaluation = "zuko"
        z_z, l_z = net.flow_forward(h)
        back_z = net.flow_inverse(z_z)
    FlowNet.evaluation = "direct"
    result["same_weights_max_abs_diff"] = {"z": float((z_d - z_z).abs().max()), "ladj": float((l_d - l_z).abs().max()),
                                           "inverse": float((back_d - back_z).abs().max())}
    d, z = result["paths"]["direct"], result["paths"]["zuko"]
    result["speedup_direct_over_zuko"] = {k: round(z[k] / d[k], 2)
                                          for k in ("ms_per_epoch", "decode_1row_us", "encode_256rows_us")}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(json.dumps({"speedup_direct_over_zuko": result["speedup_direct_over_zuko"],
                      "same_weights_max_abs_diff": result["same_weights_max_abs_diff"]}, indent=2))


if __name__ == "__main__":
    main()
