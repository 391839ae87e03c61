"""Re-sorting each run's particles every N substeps against never (Taichi, tiled scatter, issue 16).

The tiled scatter's tiles are 256 consecutive particles; as a run deforms they spread and fall back to global
atomics unless the particles are re-sorted into the curve order of their current cells
(``taichi_resort_every``; ``invphys_anisompm/backends/taichi_resort.py``). On ``--runs`` random parameter
vectors (seed 0) this simulates the same runs with each ``--every`` value in turn, the first value once
more at the end (GPU float atomics alone make two runs of the same parameters differ: that spread is the
yardstick), and records per setting the wall seconds per run (lock-step batches of ``--batch``, after an
untimed two-run pass), the ratio to the paper's 156 s, the re-sorts done, and the features' agreement
with the first setting.

    python examples/anisompm/benchmarks/bench_resort.py --preset paper --runs 128 --batch 64 --every 0 128 32 \\
        --out examples/anisompm/benchmarks/results/resort_paper_h100.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import shlex
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm", ROOT / "benchmarks",
          Path(__file__).parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import emit  # noqa: E402
from bench_tiled_p2g import PAPER_SECONDS_PER_RUN, feature_agreement, timed_features  # noqa: E402


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--arch", default="cuda", help="cpu: a check of the script (times mean nothing there)")
    p.add_argument("--runs", type=int, default=128)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--frames", type=int, default=None, help="override the preset's frames (shorter runs)")
    p.add_argument("--every", type=int, nargs="+", default=[0, 128],
                   help="taichi_resort_every values, compared with the first")
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.runs, space.dim)))
    cfg = {"backend": "taichi", "preset": a.preset, "arch": a.arch, "batch_size": a.batch,
           **({"frames": a.frames} if a.frames else {})}
    if a.arch == "cpu":
        cfg["taichi_p2g"] = "atomic"
    sims = {every: OrangePeelSimulator(**cfg, taichi_resort_every=every) for every in dict.fromkeys(a.every)}
    first = sims[a.every[0]]
    ident = RunIdentity.of(first)
    ex = OrangePeelFeatures()
    settings = [*a.every, a.every[0]]
    rows, feats = [], []
    for i, every in enumerate(settings):
        sim = sims[every]
        wall, f = timed_features(sim, params, ex)
        backend = sim.engine.backend(min(a.batch, a.runs))
        row = {"resort_every": every, "again": i == len(settings) - 1, "seconds_per_run": wall / a.runs,
               "x_paper_156s": PAPER_SECONDS_PER_RUN * a.runs / wall,
               "sorts": backend.resorter.sorts if backend.resorter is not None else 0,
               "failed": int((~np.all(np.isfinite(f), axis=1)).sum())}
        if i:
            row["features_vs_first"] = feature_agreement(feats[0], f, ex.feature_names)
        rows.append(row)
        feats.append(f)
        agree = row.get("features_vs_first", {}).get("median_rel_diff_all")
        print(f"resort_every {every}: {row['seconds_per_run']:.4f} s/run, {row['sorts']} sorts, median rel diff "
              f"vs first {agree}", flush=True)
    out = {"benchmark": "bench_resort", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "simulator_version": ident.version, "config_hash": ident.config, "preset": a.preset, "runs": a.runs,
           "batch": a.batch, "frames": first.frames, "device": first.engine.device,
           "scatter": first.engine.backend(min(a.batch, a.runs)).p2g, "rows": rows}
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
