"""What handing a trajectory to an extraction process costs the thread that drives the GPU (issue 16).

The dataset pipeline hands each finished run's trajectory to :class:`ExtractionPool` from the thread that
runs the simulator's streaming loop. Pickled, a paper-preset trajectory (25 recorded frames of 51,104
particles: ~20 MB) is copied into the pickle by the pool's feeder thread while it holds the GIL, and the
loop waits for the GIL meanwhile. Through shared memory (``min_shared_bytes``) a stager thread copies the
arrays into a reusable block with the GIL released.

This script stands a busy Python loop in for the streaming loop, hands ``--runs`` full-sized synthetic
trajectories to a pool (one every ``--every`` s) with a worker that does nothing but read them, and reports
how much of the loop's progress each hand-off cost (against the loop alone), and the ``submit`` call's own
time, for each mode, in alternating rounds::

    python benchmarks/bench_extract_handoff.py --runs 40 --rounds 2 \\
        --out benchmarks/results/extract_handoff_cpu.json
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


class ReadOnlyFeatures:
    """A stand-in extractor: touches every recorded frame (as a real one reads them) and returns 3 numbers."""

    def extract(self, trajectory):
        pos, dmg = trajectory.positions, trajectory.damage
        return np.array([float(pos[:, ::997].sum()), float(dmg[:, ::997].sum()), float(len(pos))])


def synthetic_trajectory(frames: int, particles: int, seed: int):
    """A full-sized trajectory: float32 positions (F, N, 3) and damage (F, N), int8 labels, two series."""
    from invphys.core.results import TimeSeries, Trajectory

    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 30.0
    return Trajectory(series={"separation": TimeSeries(times=t, values=rng.random(frames))},
                      positions=rng.random((frames, particles, 3), dtype=np.float32),
                      damage=rng.random((frames, particles), dtype=np.float32),
                      labels=rng.integers(0, 2, particles).astype(np.int8),
                      frame_indices=np.arange(frames) * 10, fps=30.0)


class BusyLoop:
    """A thread counting Python loop iterations (the streaming loop's stand-in)."""

    def __init__(self) -> None:
        self.count, self._stop = 0, False
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop:
            for _ in range(200):
                pass
            self.count += 1

    def rate(self, seconds: float) -> float:
        c0, t0 = self.count, time.perf_counter()
        time.sleep(seconds)
        return (self.count - c0) / (time.perf_counter() - t0)

    def __enter__(self) -> BusyLoop:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop = True
        self._thread.join()


def one_mode(mode: str, trajectories: list, every: float, workers: int) -> dict:
    from invphys.plugins.executors._extract_pool import ExtractionPool

    min_shared = None if mode == "pickle" else 1 << 20
    with ExtractionPool(ReadOnlyFeatures(), workers, min_shared_bytes=min_shared) as pool:
        list(pool._pool.map(int, range(2 * workers)))   # workers started before timing
        with BusyLoop() as loop:
            base = loop.rate(1.0)
            submit_s, futures = 0.0, []
            c0, t0 = loop.count, time.perf_counter()
            for traj in trajectories:
                ts = time.perf_counter()
                futures.append(pool.extract(traj))
                submit_s += time.perf_counter() - ts
                time.sleep(every)
            feats = [f.result() for f in futures]
            wall = time.perf_counter() - t0
            done = loop.count - c0
        blocks = pool._blocks.created if pool._blocks is not None else 0
    n = len(trajectories)
    lost_s = max(0.0, wall - done / base)
    return {"mode": mode, "runs": n, "wall_s": round(wall, 3), "loop_progress": round(done / (base * wall), 4),
            "loop_ms_lost_per_run": round(1e3 * lost_s / n, 2), "submit_ms_per_run": round(1e3 * submit_s / n, 3),
            "blocks_created": blocks, "features_checksum": float(np.sum(feats))}


def main() -> None:
    from _machine import cpu_name, emit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--frames", type=int, default=26)
    ap.add_argument("--particles", type=int, default=51104)
    ap.add_argument("--every", type=float, default=0.05, help="seconds between hand-offs")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    trajs = [synthetic_trajectory(args.frames, args.particles, seed=i % 4) for i in range(args.runs)]
    mb = (trajs[0].positions.nbytes + trajs[0].damage.nbytes) / 2**20
    rows = []
    for r in range(args.rounds):
        for mode in ("pickle", "shared"):
            row = one_mode(mode, trajs, args.every, args.workers)
            row["round"] = r + 1
            rows.append(row)
            print(row, flush=True)
    assert len({row["features_checksum"] for row in rows}) == 1, "the modes extracted different features"
    emit({"benchmark": "extract_handoff", "date": time.strftime("%Y-%m-%d"),
          "command": "python benchmarks/bench_extract_handoff.py " + " ".join(sys.argv[1:]),
          "device": f"cpu: {cpu_name()} ({os.cpu_count()} cores)", "trajectory_mb": round(mb, 2),
          "frames": args.frames, "particles": args.particles, "every_s": args.every, "workers": args.workers,
          "results": rows}, args.out)


if __name__ == "__main__":
    main()
