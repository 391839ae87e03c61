"""Inverter bundle: load time, per-target latency of the default method, and batched throughput.

    python benchmarks/bench_invert.py --bundle inverters/orange_peel_paper \
        [--repeat 5] [--single 200] [--batch 10000] [--out benchmarks/results/invert_orange_peel_paper.json]

* load: ``import invphys; invphys.load_inverter(BUNDLE)`` in fresh processes (median of --repeat), and
  the same plus the first answer (``--feature`` style mapping) - what ``invphys invert`` pays once;
* single: ``inv.invert(target)`` one target at a time, after one warm-up call (median and p90);
* amortised: ``inv.invert_many(targets)`` on --single targets at once, time per target (with result objects);
* batched: ``inv.invert_array(Y)`` on --batch targets (theta only), targets per second (median of 3),
  with 1 and 2 BLAS threads (``--threads``); the headline is 1 thread (``load_inverter``'s default).

Single, amortised and batched are measured in ``--rounds`` rounds (default 3); the medians are
reported. The machine is shared: the load averages (start, end, and after each round) are recorded.

Targets are the bundle's held-out partition (``data/test.npz``), resampled with replacement to the
sizes asked. Heavy modules imported by loading and answering are listed (the default path needs no torch).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _machine import cpu_name

HEAVY = ("torch", "stable_baselines3", "taichi", "warp", "zuko", "cma", "sbi", "sklearn", "scipy.stats")


def _git() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def load_times(bundle: str, repeat: int, method: str | None = None) -> dict:
    probe = ("import time, sys, json; t0 = time.perf_counter()\n"
             "import invphys, numpy as np\n"
             f"inv = invphys.load_inverter({bundle!r}); t1 = time.perf_counter()\n"
             "_, y = inv.bundle.data('test')\n"
             f"inv.invert(dict(zip(inv.feature_names, map(float, y[0]))), method={method!r}); t2 = time.perf_counter()\n"
             f"print(json.dumps({{'load': t1 - t0, 'first': t2 - t0, 'heavy': [m for m in {HEAVY!r} "
             "if m in sys.modules]}))")
    runs = []
    for _ in range(repeat):
        out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
        if out.returncode:
            raise SystemExit(f"loading {bundle} failed:\n{out.stderr.strip()}")
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return {"load_s_median": round(statistics.median(r["load"] for r in runs), 3),
            "load_s_runs": [round(r["load"], 3) for r in runs],
            "load_and_first_answer_s_median": round(statistics.median(r["first"] for r in runs), 3),
            "heavy_modules_imported": runs[-1]["heavy"]}


def measure(inv, method: str, single, big, threads: list[int]) -> dict:
    """One round: single-target latency, amortised time per target, batched throughput per thread count."""
    import numpy as np

    names = inv.feature_names
    inv.threads = 1
    inv.invert(dict(zip(names, map(float, single[0]), strict=True)), method=method)  # warm-up
    lat, r_surr = [], []
    for row in single:
        t0 = time.perf_counter()
        res = inv.invert(dict(zip(names, map(float, row), strict=True)), method=method)
        lat.append(time.perf_counter() - t0)
        r_surr.append(res.r_surrogate)
    t0 = time.perf_counter()
    many = inv.invert_many(single, method=method)
    amortised = (time.perf_counter() - t0) / len(single)
    batched = {}
    for n in threads:
        inv.threads = n
        inv.invert_array(big[:100], method=method)
        runs = []
        for _ in range(3):
            t0 = time.perf_counter()
            theta = inv.invert_array(big, method=method)
            runs.append(time.perf_counter() - t0)
        assert theta.shape == (len(big), inv.parameter_space.dim) and np.all((theta >= 0) & (theta <= 1))
        batched[n] = len(big) / statistics.median(runs)
    inv.threads = 1
    # the three paths answer alike
    np.testing.assert_allclose([r.theta for r in many], inv.invert_array(single, method=method), atol=1e-9)
    lat_ms = np.array(lat) * 1e3
    return {"single_ms_median": float(np.median(lat_ms)), "single_ms_p90": float(np.percentile(lat_ms, 90)),
            "amortised_ms_per_target": amortised * 1e3, "batched_targets_per_s": batched,
            "mean_r_surrogate_heldout": float(np.mean(r_surr)), "loadavg_1min": os.getloadavg()[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default="inverters/orange_peel_paper")
    ap.add_argument("--repeat", type=int, default=5, help="fresh processes for the load time")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of the in-process measurements (median reported)")
    ap.add_argument("--single", type=int, default=200)
    ap.add_argument("--batch", type=int, default=10000)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="BLAS threads for the batched path")
    ap.add_argument("--method", default=None, help="default: the bundle's default method")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    import numpy as np

    import invphys

    load_start = list(os.getloadavg())
    load = load_times(args.bundle, args.repeat, args.method)
    inv = invphys.load_inverter(args.bundle)
    method = args.method or inv.default_method
    _, y = inv.bundle.data("test")
    rng = np.random.default_rng(0)
    single = y[rng.integers(0, len(y), args.single)]
    big = y[rng.integers(0, len(y), args.batch)]
    rounds = [measure(inv, method, single, big, args.threads) for _ in range(args.rounds)]

    def med(key: str, nd: int) -> float:
        return round(statistics.median(r[key] for r in rounds), nd)

    per_threads = {str(n): round(statistics.median(r["batched_targets_per_s"][n] for r in rounds), 1)
                   for n in args.threads}
    best = max(per_threads, key=per_threads.get)
    default = "1" if "1" in per_threads else best  # load_inverter's default: one BLAS thread
    m = inv.bundle.manifest
    result = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "bundle": args.bundle, "bundle_id": m.get("bundle_id"), "method": method,
        "simulator": f"{m['simulator']['name']} {m['simulator']['version']}",
        "dataset_fingerprint": m["dataset"]["fingerprint"],
        **load,
        "rounds": args.rounds,
        "single_ms_median": med("single_ms_median", 3),
        "single_ms_p90": med("single_ms_p90", 3),
        "single_targets": args.single,
        "mean_r_surrogate_heldout": med("mean_r_surrogate_heldout", 4),
        "amortised_ms_per_target": med("amortised_ms_per_target", 4),
        "batched_targets": args.batch,
        "batched_targets_per_s": per_threads[default],
        "batched_blas_threads": int(default),
        "batched_targets_per_s_best": per_threads[best],
        "batched_blas_threads_best": int(best),
        "batched_targets_per_s_by_blas_threads": per_threads,
        "per_round": [{**{k: round(v, 4) for k, v in r.items() if k != "batched_targets_per_s"},
                       "batched_targets_per_s": {str(n): round(v, 1) for n, v in r["batched_targets_per_s"].items()}}
                      for r in rounds],
        "goals": {"load_s": 3.0, "amortised_ms_per_target": 5.0, "batched_targets_per_s": 10000},
        "device": {"cpu": cpu_name(), "cores": os.cpu_count(), "loadavg_at_start": load_start,
                   "loadavg_at_end": list(os.getloadavg()), "single_and_amortised_blas_threads": 1,
                   "python": platform.python_version(), "numpy": np.__version__},
        "git": _git(),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    out = args.out or Path(__file__).parent / "results" / f"invert_{Path(args.bundle).name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
