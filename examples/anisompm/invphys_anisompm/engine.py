"""Time stepping, batching, recording and failure checks: the host side shared by every backend.

:class:`Engine` advances the runs of a :class:`~invphys_anisompm.model.Model` together: each run keeps
its own time step (:func:`run_dt_bound`) for the whole run unless its particles move too fast (the
velocity guard raises a frame's substeps), runs of similar cost are batched together
(:meth:`Engine.run_batched`), and every frame ends with device reductions (peak speed, kinetic energy,
per-body centroid and mean damage, force and work on every collider and grip) and failure checks.
The time step plan lives in :mod:`invphys_anisompm.stepping` and :class:`RunRecord` in
:mod:`invphys_anisompm.record` (both re-exported here), so that :mod:`invphys_anisompm.streaming` need not
import this module.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from invphys_anisompm.failure import BODY0, STAT_KE, STAT_VMAX, energy_bound, frame_failure, substep_failure
from invphys_anisompm.model import Model
from invphys_anisompm.record import RunRecord
from invphys_anisompm.scene import Scene, SceneError
from invphys_anisompm.stepping import (
    dt_bounds,
    estimated_substeps,
    frame_plan,
    kinematic_speed,
    kinematic_table,
    run_dt_bound,
    velocity_guard,
    velocity_guard_one,
)


class Engine:
    """Runs batches of a scene on one backend.

    Args:
        scene: the built :class:`~invphys_anisompm.scene.Scene`.
        backend: ``"taichi"`` or ``"warp"``.
        arch: ``"cpu"``, ``"cuda"`` or ``"auto"`` (CUDA if present).
        allow_cpu_fallback: run on the CPU when CUDA is asked for but absent.
        cost_estimator: ``f(model, frames) -> (n_runs,)`` estimated slot-substeps of each run (what
            batches are sorted by and continuous batching's queue is ordered by); default
            :func:`estimated_substeps` (exact unless the velocity guard binds).
        backend_options: passed to the backend (Warp: ``use_graphs``, ``gpu_deterministic``).
    """

    def __init__(self, scene: Scene, backend: str = "taichi", arch: str = "cpu", allow_cpu_fallback: bool = False,
                 cost_estimator: Callable[[Model, int], np.ndarray] | None = None, **backend_options: Any) -> None:
        self.scene = scene
        self.cost_estimator = cost_estimator
        self.backend_name = backend
        self.arch = arch
        self.allow_cpu_fallback = allow_cpu_fallback
        self.backend_options = backend_options
        self._backends: dict[int, Any] = {}
        self._streaming: set[int] = set()   # slot counts whose backend a live stream holds
        #: slot-substep accounting of every batch run so far (``useful``, ``launched``, ``efficiency``)
        from invphys_anisompm.streaming import SlotCounters

        self.counters = SlotCounters()

    def ensure_free(self, batch: int) -> None:
        """Raise :class:`EngineBusyError` if a live stream holds the ``batch``-slot backend."""
        from invphys_anisompm.streaming import EngineBusyError

        if batch in self._streaming:
            raise EngineBusyError(f"this engine's {batch}-slot backend is serving a stream that has not finished: "
                                  "exhaust or close() that stream first (or use another engine)")

    def claim_slots(self, batch: int) -> None:
        """Mark the ``batch``-slot backend as serving a stream (raises if it already is)."""
        self.ensure_free(batch)
        self._streaming.add(batch)

    def release_slots(self, batch: int) -> None:
        """The ``batch``-slot backend's stream has ended."""
        self._streaming.discard(batch)

    def backend(self, batch: int) -> Any:
        """The backend object for batches of ``batch`` runs (allocated once per size)."""
        if batch not in self._backends:
            from invphys_anisompm.backends import load_backend

            cls = load_backend(self.backend_name)
            self._backends[batch] = cls(self.scene, batch, arch=self.arch, allow_cpu_fallback=self.allow_cpu_fallback,
                                        **self.backend_options)
        return self._backends[batch]

    def estimate_cost(self, model: Model, frames: int) -> np.ndarray:
        """(n_runs,) estimated slot-substeps of each run of ``model`` (settling included)."""
        f = self.cost_estimator or estimated_substeps
        return np.asarray(f(model, frames), float).reshape(model.n_envs)

    @property
    def device(self) -> str:
        return next(iter(self._backends.values())).device if self._backends else ""

    def run_batched(self, model: Model, frames: int, record_every: int, batch_size: int,
                    on_result: Callable[[int, RunRecord], None] | None = None) -> list[RunRecord]:
        """Every run of ``model``, ``batch_size`` at a time, cheapest first; records in model order.
        ``on_result(i, record)`` is called as soon as run ``i``'s batch ends."""
        order = np.argsort(self.estimate_cost(model, frames), kind="stable")
        out: list[RunRecord | None] = [None] * model.n_envs
        for start in range(0, len(order), batch_size):
            idx = order[start:start + batch_size]
            records = self.run(model.take(idx), frames, record_every)
            for i, rec in zip(idx, records, strict=True):
                out[int(i)] = rec
                if on_result is not None:
                    on_result(int(i), rec)
        return [r for r in out if r is not None]

    def stream(self, model: Model, frames: int, record_every: int, batch_size: int, min_chunk: int = 1,
               queue_order: str = "longest_first", cost: np.ndarray | None = None):
        """Continuous batching: yield ``(i, record)`` for every run of ``model`` as it finishes, with
        ``batch_size`` slots kept full (see :mod:`invphys_anisompm.streaming`). ``queue_order``:
        ``longest_first`` (by ``cost``, default :meth:`estimate_cost`) or ``given`` (row order)."""
        from invphys_anisompm.streaming import QUEUE_ORDERS, stream_runs

        if queue_order not in QUEUE_ORDERS:  # checked here, not at the generator's first step
            raise SceneError(f"unknown queue order {queue_order!r}; known: {', '.join(QUEUE_ORDERS)}")
        return stream_runs(self, model, frames, record_every, batch_size, min_chunk=min_chunk,
                           counters=self.counters, order=queue_order, cost=cost)

    def stream_feed(self, feeder: Callable[[int], Model | None], frames: int, record_every: int, batch_size: int,
                    min_chunk: int = 1):
        """Continuous batching over an open stream: ``feeder(free)`` gives a :class:`Model` of new runs whenever
        slots are free (None: none ready yet); yields ``(i, record)``, ``i`` counting fed runs from 0 (see
        :func:`invphys_anisompm.streaming.feed_runs`)."""
        from invphys_anisompm.streaming import feed_runs

        return feed_runs(self, feeder, frames, record_every, batch_size, min_chunk=min_chunk, counters=self.counters)

    def run(self, model: Model, frames: int, record_every: int) -> list[RunRecord]:
        """Simulate every run of ``model`` as one batch: settling, then ``frames`` frames, recording
        particles every ``record_every`` frames (and the last); returns one record per run."""
        scene, o = self.scene, self.scene.options
        B = model.n_envs
        self.ensure_free(B)
        backend = self.backend(B)
        fresh = bool(getattr(backend, "reads_are_new", False))
        start = time.perf_counter()
        backend.load(model.table(), model.friction)
        records = [RunRecord() for _ in range(B)]
        dx, fps = o.dx, o.fps
        lo, hi = 1.5 * dx, o.domain - 1.5 * dx
        nsub_run, dt_run = frame_plan(fps, run_dt_bound(model, frames))
        bounds = energy_bound(model.total_mass(), model.wave_speed(), kinematic_speed(scene, frames), o.energy_factor)
        alive = np.ones(B, bool)
        names = scene.kinematic_names
        work = np.zeros((B, len(names)))
        last_force = np.zeros((B, len(names), 3))
        counts = np.array([max(b.count, 1) for b in scene.bodies], float)
        for b in range(B):
            records[b].dt = float(dt_run[b])

        def step_frame(frame: int, settling: bool, stats: np.ndarray) -> np.ndarray:
            nsub = velocity_guard(nsub_run, stats[:, STAT_VMAX], dx, fps, o.velocity_cfl)
            dt = (1.0 / fps) / nsub
            for b in np.flatnonzero(alive):
                reason = substep_failure(int(nsub[b]), o.max_substeps_per_frame, frame, float(stats[b, STAT_VMAX]))
                if reason:
                    records[b].failure, alive[b] = reason, False
                elif nsub[b] > nsub_run[b]:
                    records[b].guard_frames += 1
            nsub = np.where(alive, nsub, 0)
            if not alive.any():
                return stats
            if settling:
                kin = np.zeros((B, int(max(1, nsub.max())), max(len(names), 1), 6))
            else:
                kin = kinematic_table(scene, frame, nsub, dt, alive)
            backend.set_frame(dt, nsub, kin, damage_on=not settling, damping=o.settle_damping if settling else 0.0)
            backend.advance(int(nsub.max()))
            self.counters.useful += int(nsub.sum())
            self.counters.launched += B * int(nsub.max())
            self.counters.chunks += 1
            stats = backend.frame_stats(lo, hi)
            imp, w = backend.kinematic_sums()
            last_force[:] = imp * fps   # mean force over the frame: impulse / frame time
            if not settling:
                work[:] += w
            for b in np.flatnonzero(alive):
                if settling:
                    records[b].settle_substeps += int(nsub[b])
                else:
                    records[b].substeps += int(nsub[b])
                reason = frame_failure(stats[b], float(bounds[b]), frame + 1,
                                       float(np.sum(imp[b])) + float(np.sum(w[b])))
                if reason:
                    records[b].failure, alive[b] = reason, False
            return stats

        def record(frame: int, stats: np.ndarray, recorded: bool) -> None:
            x = d = None
            host = [r for r in scene.reductions if frame % r.every == 0]
            if recorded or host:
                x, d = backend.read()
            host_vals = {r.name: np.asarray(r.fn(x, d, scene), float).reshape(B, -1) for r in host}
            t = frame / fps
            moved = [path.displacement(t) for path in scene.kinematic_paths]  # the same for every run
            for b in np.flatnonzero(alive):
                s = records[b].series
                s.setdefault("max_speed", []).append(float(stats[b, STAT_VMAX]))
                s.setdefault("kinetic_energy", []).append(float(stats[b, STAT_KE]))
                for i, body in enumerate(scene.bodies):
                    col = BODY0 + 4 * i
                    s.setdefault(f"centroid/{body.name}", []).append(stats[b, col:col + 3] / counts[i])
                    s.setdefault(f"mean_damage/{body.name}", []).append(float(stats[b, col + 3] / counts[i]))
                for c, name in enumerate(names):
                    s.setdefault(f"force/{name}", []).append(last_force[b, c].copy())
                    s.setdefault(f"work/{name}", []).append(float(work[b, c]))
                    s.setdefault(f"position/{name}", []).append(moved[c].copy())
                for name, vals in host_vals.items():
                    v = vals[b]
                    s.setdefault(name, []).append(float(v[0]) if v.size == 1 else v.copy())
                if recorded:   # views of this frame's new arrays where the backend made them
                    records[b].positions.append(x[b] if fresh else x[b].copy())
                    records[b].damage.append(d[b] if fresh else d[b].copy())
                    records[b].frames.append(frame)

        stats = backend.frame_stats(lo, hi)
        backend.kinematic_sums()
        for s in range(round(o.settle_seconds * fps)):
            stats = step_frame(-1 - s, True, stats)
            if not alive.any():
                break
        record(0, stats, True)
        for frame in range(frames):
            if not alive.any():
                break
            stats = step_frame(frame, False, stats)
            record(frame + 1, stats, (frame + 1) % record_every == 0 or frame + 1 == frames)
        backend.sync()
        wall = time.perf_counter() - start
        for r in records:
            r.wall_time_s = wall / B
            if r.failure is not None:
                r.positions, r.damage = [], []
        return records


__all__ = ["Engine", "RunRecord", "dt_bounds", "estimated_substeps", "frame_plan", "kinematic_table", "run_dt_bound",
           "velocity_guard", "velocity_guard_one"]
