"""A substep's time against the number of runs still active in a lock-step batch (issue 16).

A lock-step batch keeps launching substeps until its slowest run has finished its frame; the runs past their
own substep count idle. How much a substep costs with 64, 32, ..., 1, 0 runs active says what the batch's
tail costs and what bounds it. For each count ``a`` (the first ``a`` slots of a ``--batch`` of random runs
active, the rest idle), ``--steps`` substeps are launched back to back with one sync at the end:

- ``gpu_ms``: wall milliseconds per substep, sync included (the GPU's time when it is the bound);
- ``host_ms``: milliseconds per substep until the launches have been issued (Python + Taichi's launch path;
  the floor when the GPU is faster);
- ``ms_per_active_run``: ``gpu_ms / a``, against the full batch's;
- ``stage_ms``: each stage's milliseconds, synchronised one by one (``kernel_times``).

``--frames F`` first simulates F frames of the batch, so that the state is deformed and fractured as a
batch's tail finds it (else the state at rest). With particle re-sorting on (``--resort-every``, the tiled
scatter's default), the state is sorted once more before the timed substeps (none sorts during them) and
``resort_ms`` records one sort of the whole batch.

    python benchmarks/bench_active_runs.py --preset paper --batch 64 --out $OUT/active_runs_paper.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import shlex
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm", Path(__file__).parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import emit  # noqa: E402


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--arch", default="cuda", help="cpu: a check of the script (times mean nothing there)")
    p.add_argument("--p2g", default="auto", choices=["auto", "atomic", "tiled"], help="the scatter")
    p.add_argument("--resort-every", type=int, default=None,
                   help="substeps between particle re-sorts (taichi_resort_every; default: the simulator's)")
    p.add_argument("--steps", type=int, default=40, help="substeps timed per count of active runs")
    p.add_argument("--frames", type=int, default=0,
                   help="simulate this many frames first (a deformed, partly fractured state; 0: the state at rest)")
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def active_counts(batch: int) -> list[int]:
    """The full batch, halved down to one run, then none."""
    counts, a = [], batch
    while a >= 1:
        counts.append(a)
        a //= 2
    return [*counts, 0]


def time_substeps(backend, active: int, steps: int, nk: int) -> tuple[float, float]:
    """(host seconds to issue, wall seconds to finish) per substep with the first ``active`` runs active,
    through ``backend.advance`` (the path whole runs take)."""
    B = backend.batch
    nsub = np.where(np.arange(B) < active, steps, 0)
    backend.set_frame(np.full(B, 1e-5), nsub, np.zeros((B, steps, nk, 6)), damage_on=True)
    backend.advance(steps)  # warm (and compile whatever this number of substeps launches)
    backend.sync()
    t0 = time.perf_counter()
    backend.advance(steps)
    t1 = time.perf_counter()
    backend.sync()
    t2 = time.perf_counter()
    return (t1 - t0) / steps, (t2 - t0) / steps


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.batch, space.dim)))
    sim = OrangePeelSimulator(backend="taichi", preset=a.preset, arch=a.arch, batch_size=a.batch, taichi_p2g=a.p2g,
                              taichi_resort_every=a.resort_every)
    ident = RunIdentity.of(sim)
    backend = sim.engine.backend(a.batch)
    model = model_for(sim.engine_scene, params)
    if a.frames:
        sim.engine.run(model, a.frames, a.frames)  # leaves the batch's state at frame a.frames
    else:
        backend.load(model.table(), model.friction)
    sort_ms = None
    if backend.resorter is not None:  # sorted now, then not again while substeps are timed
        backend.resorter.sort()
        backend.sync()
        t0 = time.perf_counter()
        for _ in range(5):
            backend.resorter.sort()
        backend.sync()
        sort_ms = (time.perf_counter() - t0) / 5 * 1e3
        backend.resorter.every = 0
        print(f"one re-sort of the batch's particles: {sort_ms:.3f} ms", flush=True)
    nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
    rows = []
    for active in active_counts(a.batch):
        host, wall = time_substeps(backend, active, a.steps, nk)
        stage_ms = {k: v * 1e3 for k, v in backend.kernel_times(5).items()}  # each stage synchronised
        rows.append({"active_runs": active, "gpu_ms": wall * 1e3, "host_ms": host * 1e3,
                     "ms_per_active_run": wall * 1e3 / active if active else None, "stage_ms": stage_ms})
        print(f"{active:3d} active: {wall * 1e3:.3f} ms per substep (host {host * 1e3:.3f} ms); stages "
              + ", ".join(f"{k} {v:.3f}" for k, v in stage_ms.items()), flush=True)
    full = rows[0]["ms_per_active_run"]
    for r in rows:
        r["cost_per_run_vs_full"] = r["ms_per_active_run"] / full if r["active_runs"] else None
    out = {"benchmark": "bench_active_runs", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "simulator_version": ident.version, "config_hash": ident.config, "preset": a.preset, "batch": a.batch,
           "state": f"after {a.frames} frames" if a.frames else "at rest",
           "scatter": backend.p2g, "resort_every": backend.resort_every, "resort_ms": sort_ms,
           "device": backend.device, "steps": a.steps, "rows": rows}
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
