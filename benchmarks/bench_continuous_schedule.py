"""Scheduling study of continuous batching on the CPU, without physics: a null backend.

The engine's host loop (:func:`invphys_anisompm.streaming.stream_runs` and the lock-step
:meth:`Engine.run_batched`) drives a backend whose kernels do nothing: no particle moves, so the
velocity guard never binds and every run costs exactly its estimated substeps (as measured on the GPU
for the orange peel's paper preset: mean 5,828, min 1,008, max 40,572 over the 256 random runs of
seed 0). What it measures is the schedule alone: slot efficiency (useful slot-substeps over
``batch * substeps launched``), host chunks (round trips), substep launches, and the lower bound
``sum(cost) / (batch * max(cost))`` that no queue order can beat (one run longer than a slot's fair
share finishes alone).

Example::

    python benchmarks/bench_continuous_schedule.py --runs 256 512 2000 --batch 64 32

Writes ``benchmarks/results/continuous_schedule_<preset>_cpu.json`` (or ``--out``).
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


class NullBackend:
    """The backend interface with no physics: zero statistics and sums, particles stay put. Counts
    substep launches and active slot-substeps (what a backend whose idle slots are free would pay)."""

    name = "null"
    device = "null"

    def __init__(self, scene, batch: int) -> None:
        from invphys_anisompm.failure import n_stats

        self.batch = batch
        self.nstats = n_stats(len(scene.bodies))
        self.nk = len(scene.kinematic_names)
        self._nsub = np.zeros(batch, np.int64)
        self.launches = 0

    def load(self, table, friction) -> None:
        pass

    def load_slots(self, slots, table, friction) -> None:
        pass

    def set_frame(self, dt, nsub, kin, damage_on, damping=0.0) -> None:
        self._nsub = np.asarray(nsub, np.int64)

    def advance(self, n_steps: int) -> None:
        self.launches += int(n_steps)

    def frame_stats(self, lo, hi, slots=None) -> np.ndarray:
        return np.zeros((self.batch, self.nstats))

    def kinematic_sums(self, slots=None):
        n = self.batch if slots is None else len(slots)
        return np.zeros((n, self.nk, 3)), np.zeros((n, self.nk))

    def frame_end(self, lo, hi, slots):
        return (self.frame_stats(lo, hi, slots), *self.kinematic_sums(slots))

    def read_slots(self, slots):
        return np.zeros((len(slots), 1, 3), np.float32), np.zeros((len(slots), 1), np.float32)

    def read(self):
        return np.zeros((self.batch, 1, 3), np.float32), np.zeros((self.batch, 1), np.float32)

    def sync(self) -> None:
        pass


def schedule(engine, model, frames: int, batch: int, scheduling: str, order: str = "longest_first",
             min_chunk: int = 1) -> dict:
    """One schedule's counters (the engine's ``_backends`` hold null backends)."""
    from invphys_anisompm.streaming import SlotCounters

    engine.counters = SlotCounters()
    t0 = time.perf_counter()
    finish = []
    if scheduling == "lockstep":
        engine.run_batched(model, frames, 10**9, batch, on_result=lambda i, r: finish.append(i))
    else:
        finish = [i for i, _ in engine.stream(model, frames, 10**9, batch, min_chunk=min_chunk, queue_order=order)]
    c = engine.counters
    return {"scheduling": scheduling, "queue_order": order if scheduling == "continuous" else "cost_sorted_batches",
            "batch": batch, "min_chunk": min_chunk if scheduling == "continuous" else None,
            "slot_efficiency": c.efficiency, "host_chunks": c.chunks, "substep_launches": c.launched // batch,
            "useful_slot_substeps": c.useful, "idle_slot_substeps": c.launched - c.useful,
            "host_loop_s": time.perf_counter() - t0, "runs_done": len(finish)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--runs", type=int, nargs="+", default=[256, 512, 2000])
    ap.add_argument("--batch", type=int, nargs="+", default=[64, 32])
    ap.add_argument("--min-chunk", type=int, nargs="+", default=[1, 16, 32])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from invphys_anisompm import Engine
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.simulator import OrangePeelSimulator

    sim = OrangePeelSimulator(preset=args.preset, arch="cpu")
    scene = sim.engine_scene.engine
    space = sim.parameter_space()
    rows = []
    for runs in args.runs:
        params = space.denormalize(np.random.default_rng(args.seed).uniform(size=(runs, space.dim)))
        model = model_for(sim.engine_scene, params)
        engine = Engine(scene, backend="taichi", arch="cpu")
        # every batch size the engine asks for (a last, smaller lock-step batch too) gets a null backend
        engine.backend = lambda b, e=engine: e._backends.setdefault(b, NullBackend(scene, b))
        cost = engine.estimate_cost(model, sim.frames)
        for batch in args.batch:
            bound = float(cost.sum() / (batch * cost.max()))
            cases = [("lockstep", "longest_first", 1)] + [("continuous", o, m) for m in args.min_chunk
                                                          for o in ("given", "longest_first")]
            for sched, order, mc in cases:
                row = schedule(engine, model, sim.frames, batch, sched, order, mc)
                row.update(runs=runs, efficiency_bound=min(bound, 1.0), cost_mean=float(cost.mean()),
                           cost_max=float(cost.max()))
                rows.append(row)
                print(f"runs {runs:5d} B {batch:3d} {sched:10s} {row['queue_order']:19s} mc {mc:3d}: "
                      f"eff {row['slot_efficiency']:.3f} (bound {row['efficiency_bound']:.3f}) "
                      f"chunks {row['host_chunks']:6d} launches {row['substep_launches']:7d}", flush=True)
    out = {
        "benchmark": "bench_continuous_schedule",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_continuous_schedule.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "device": "cpu (null backend: schedule only, no physics)", "host": platform.processor() or platform.machine(),
        "simulator": sim.name, "simulator_version": sim.version, "preset": args.preset, "frames": sim.frames,
        "config_hash": __import__("invphys.core.dataset", fromlist=["RunIdentity"]).RunIdentity.of(sim).config,
        "seed": args.seed, "rows": rows,
    }
    path = args.out or ROOT / "benchmarks" / "results" / f"continuous_schedule_{args.preset}_cpu.json"
    path.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
