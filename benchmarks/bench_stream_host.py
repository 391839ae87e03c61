"""Continuous batching's own host work, with a backend that does nothing (issue 16). CPU, no physics.

``Engine.stream`` drives a do-nothing backend (the paper scene's shapes: statistics, kinematic tables, recorded
frames of zeros) through random runs' planned frames, so every second measured is the streaming loop's Python.
On a GPU, the host's work between a chunk's frame end (``backend.frame_end``: a synchronising read) and the next
launch (``backend.advance``) is time the GPU waits; the host's work after a launch overlaps the chunk. The
script reports both per synchronising chunk, and the loop's wall.

Compare two versions of the engine by listing an older copy first on ``PYTHONPATH`` (this tree's packages are
added only when absent), e.g.::

    PYTHONPATH=.gpu/old/examples/anisompm python benchmarks/bench_stream_host.py --runs 128
    python benchmarks/bench_stream_host.py --runs 128 --out benchmarks/results/stream_host_cpu.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (an older copy may come first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)


class NullBackend:
    """The backend interface ``stream_runs`` uses, doing nothing; times when the loop calls it."""

    reads_are_new = True

    def __init__(self, scene, batch: int) -> None:
        from invphys_anisompm.failure import n_stats

        self.batch, self.nstats = batch, n_stats(len(scene.bodies))
        self.nk = len(scene.kinematic_names)
        self.x = np.zeros((batch, scene.n_particles, 3), np.float32)
        self.d = np.zeros((batch, scene.n_particles), np.float32)
        self.after_sync: list[float] = []     # host seconds from a frame end to the next launch (GPU idle)
        self.overlapped: list[float] = []     # host seconds from a launch to the next frame end (GPU busy)
        self._t_end: float | None = None
        self._t_launch: float | None = None

    def kinematic_sums(self, slots=None):
        return np.zeros((self.batch, self.nk, 3)), np.zeros((self.batch, self.nk))

    def load_slots(self, slots, table, friction) -> None:
        pass

    def frame_stats(self, lo, hi, slots=None):
        return np.zeros((self.batch, self.nstats))

    def set_frame(self, dt, nsub, kin, damage_on, damping=0.0) -> None:
        table = np.zeros((*kin.shape[:2], self.nk + 1, 6), np.float32)   # the copy a real backend makes
        table[:, :, :kin.shape[2]] = kin

    def advance(self, n_steps: int) -> None:
        now = time.perf_counter()
        if self._t_end is not None:
            self.after_sync.append(now - self._t_end)
            self._t_end = None
        self._t_launch = time.perf_counter()

    def frame_end(self, lo, hi, slots):
        now = time.perf_counter()
        if self._t_launch is not None:
            self.overlapped.append(now - self._t_launch)
        n = len(slots)
        out = np.zeros((self.batch, self.nstats)), np.zeros((n, self.nk, 3)), np.zeros((n, self.nk))
        self._t_end = time.perf_counter()
        return out

    def read_slots(self, slots):
        s = np.asarray(slots)
        return self.x[s].copy(), self.d[s].copy()


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--runs", type=int, default=128)
    ap.add_argument("--slots", type=int, default=64)
    ap.add_argument("--min-chunk", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3, help="passes; the median is reported")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    import invphys_anisompm
    from _machine import cpu_name, emit  # benchmarks/ is on the path when this runs as a script
    from invphys_anisompm.streaming import SlotCounters
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.simulator import OrangePeelSimulator

    sim = OrangePeelSimulator(preset=args.preset, arch="cpu")
    engine, scene = sim.engine, sim.engine_scene.engine
    theta = np.random.default_rng(args.seed).random((args.runs, sim.parameter_space().dim))
    model = model_for(sim.engine_scene, sim.parameter_space().denormalize(theta))
    passes = []
    for _ in range(args.repeat):
        slots = min(args.slots, args.runs)   # the stream allocates min(batch_size, runs) slots
        backend = engine._backends[slots] = NullBackend(scene, slots)
        engine.counters = SlotCounters()
        t0 = time.perf_counter()
        n = sum(1 for _ in engine.stream(model, sim.frames, sim.record_every, args.slots, min_chunk=args.min_chunk))
        wall = time.perf_counter() - t0
        passes.append({"runs": n, "wall_s": wall, "chunks": engine.counters.chunks,
                       "synchronising_chunks": len(backend.after_sync),
                       "after_sync_ms": 1e3 * float(np.mean(backend.after_sync)),
                       "overlapped_ms": 1e3 * float(np.mean(backend.overlapped))})
    med = {k: float(np.median([p[k] for p in passes])) for k in ("wall_s", "after_sync_ms", "overlapped_ms")}
    out = {"benchmark": "stream_host", "date": time.strftime("%Y-%m-%d"), "command": "python " + " ".join(sys.argv),
           "device": f"cpu:{cpu_name()} (host loop only; the backend does nothing)",
           "engine": str(Path(invphys_anisompm.__file__).parent), "simulator_version": sim.version,
           "preset": args.preset, "runs": args.runs, "slots": args.slots, "min_chunk": args.min_chunk,
           "seed": args.seed, "median": med, "passes": passes}
    emit(out, args.out)
    return out


if __name__ == "__main__":
    main()
