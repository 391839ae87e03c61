"""Continuous batching: ``B`` slots stay full; a finished (or failed) run's slot is re-initialised on the
device with the next parameter vector of the queue while the other slots keep running.

Each slot has its own frame counter, time step, substep offset within its frame, kinematic table and
feature accumulators. The host advances the batch in *chunks* of ``K`` substeps: a slot is active for
``min(K, substeps left in its frame)`` of them, so slots reach their frame ends at different times;
``K`` is the fewest substeps any slot has left in its frame (at least ``min_chunk``), so in a chunk no
slot idles unless ``min_chunk`` asks for it. At a frame end the slot's statistics, failure checks and
records are taken exactly as in :meth:`Engine.run`; a slot's force and work sums stay on the device for
the whole frame and are read (and reset) at its end, as in the lock-step path. So on the CPU with a
serialised scatter every record is bit-for-bit the lock-step one, whatever the slot, the queue order or
the other runs of the batch. Results stream out as runs finish.

The host's work is ordered around the GPU: between a frame end (a synchronising read) and the next launch
it does only what that launch needs (failure checks, the next frames' substeps, the particles a record
takes); appending the records, building the next frames' kinematic tables and handing finished runs to
the caller happen after the launch, while the chunk runs (launches are asynchronous on a GPU). A backend with
``read_slots_later`` (Taichi) starts a record's particle read at the frame end and the stream takes its
arrays after the next launch (on CUDA the copy back runs meanwhile, on a stream of its own).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from invphys_anisompm.backends import ReadyRead
from invphys_anisompm.failure import (
    BODY0,
    STAT_KE,
    STAT_VMAX,
    energy_bound,
    frame_failure,
    substep_failure,
    unhealthy,
)
from invphys_anisompm.model import Model
from invphys_anisompm.record import RunRecord
from invphys_anisompm.stepping import (
    frame_plan,
    kinematic_speed,
    kinematic_table,
    run_dt_bound,
    velocity_guard_one,
)


class SlotCounters:
    """Substep accounting of a stream: ``useful`` slot-substeps done by runs over ``launched`` ones
    (``batch * substeps launched``); ``efficiency`` is their ratio (1.0: no slot ever idled)."""

    def __init__(self) -> None:
        self.useful = 0
        self.launched = 0
        self.chunks = 0

    @property
    def efficiency(self) -> float:
        return self.useful / self.launched if self.launched else 0.0


#: orders in which the queue hands runs to free slots
QUEUE_ORDERS = ("longest_first", "given")

#: ``longest_first`` orders runs within consecutive windows of this many runs per slot, in row order
QUEUE_WINDOW_PER_SLOT = 8


def queue_order(cost: np.ndarray, order: str = "longest_first", window: int | None = None) -> np.ndarray:
    """The run indices in the order free slots take them.

    ``longest_first`` (LPT): costliest first by ``cost`` (ties in row order) within consecutive windows of
    ``window`` runs taken in row order (None: all runs one window), so the long runs of each window start at
    once instead of finishing alone at the end, and a stream stopped early (a time-limited dataset session)
    has run about the first rows, not the costliest rows of the whole design; ``given``: row order. A run's
    result never depends on its slot or start time, only the finishing order changes.
    """
    from invphys_anisompm.scene import SceneError

    if order not in QUEUE_ORDERS:
        raise SceneError(f"unknown queue order {order!r}; known: {', '.join(QUEUE_ORDERS)}")
    cost = np.asarray(cost, float)
    if order == "given":
        return np.arange(len(cost))
    step = len(cost) if window is None else max(1, int(window))
    return np.concatenate([start + np.argsort(-cost[start:start + step], kind="stable")
                           for start in range(0, len(cost), max(step, 1))] or [np.zeros(0, np.int64)])


class _Runs:
    """The inputs of a stream's runs by run number (kernel tables, frictions, substeps, dt, energy bounds);
    an open stream adds models as they are fed. Every value is per run, so a run's inputs never depend on
    which other runs were fed with it."""

    def __init__(self, engine, frames: int) -> None:
        self.engine, self.frames = engine, frames
        self.kinematic_speed = kinematic_speed(engine.scene, frames)   # the scene's, the same for every run
        self.table: np.ndarray | None = None
        self.fric: np.ndarray | None = None
        self.nsub = np.zeros(0, np.int64)
        self.dt = np.zeros(0)
        self.bound = np.zeros(0)

    def add(self, model: Model) -> list[int]:
        """Add the runs of ``model``; their run numbers."""
        scene = self.engine.scene
        o = scene.options
        nsub, dt = frame_plan(o.fps, run_dt_bound(model, self.frames))
        bound = energy_bound(model.total_mass(), model.wave_speed(), self.kinematic_speed, o.energy_factor)
        first = len(self.nsub)
        table, fric = model.table(), model.friction
        self.table = table if self.table is None else np.concatenate([self.table, table])
        self.fric = fric if self.fric is None else np.concatenate([self.fric, fric])
        self.nsub, self.dt = np.concatenate([self.nsub, nsub]), np.concatenate([self.dt, dt])
        self.bound = np.concatenate([self.bound, bound])
        return list(range(first, first + model.n_envs))


class _Queue:
    """A closed stream's runs in queue order."""

    def __init__(self, order: np.ndarray) -> None:
        self.queue = [int(i) for i in order][::-1]   # pop() = the next run

    def take(self, n: int) -> list[int]:
        return [self.queue.pop() for _ in range(min(n, len(self.queue)))]


class _Feed:
    """An open stream's runs: ``feeder(free)`` gives a model of new runs (or None: none ready now); runs fed
    beyond the free slots wait here, in feed order."""

    def __init__(self, runs: _Runs, feeder) -> None:
        self.runs, self.feeder, self.waiting = runs, feeder, []

    def take(self, n: int) -> list[int]:
        if n > len(self.waiting):
            model = self.feeder(n - len(self.waiting))
            if model is not None and model.n_envs > 0:
                self.waiting += self.runs.add(model)
        out, self.waiting = self.waiting[:n], self.waiting[n:]
        return out


class EngineBusyError(RuntimeError):
    """The engine's backend for this many slots is serving a stream that has not finished."""


def stream_runs(engine, model: Model, frames: int, record_every: int, batch_size: int, min_chunk: int = 1,
                counters: SlotCounters | None = None, order: str = "longest_first",
                cost: np.ndarray | None = None) -> Iterator[tuple[int, RunRecord]]:
    """Yield ``(i, record)`` for every run ``i`` of ``model`` as it finishes.

    ``engine`` is an :class:`~invphys_anisompm.engine.Engine` (its backend for ``min(batch_size, runs)``
    slots is reused across calls); ``min_chunk`` trades idle slot-substeps for fewer host round trips.
    ``order`` is the queue order (:func:`queue_order`, windows of :data:`QUEUE_WINDOW_PER_SLOT` runs per
    slot) over ``cost`` (per-run estimated slot-substeps; default :meth:`Engine.estimate_cost`). The slots are the stream's until it is exhausted or closed:
    another stream or lock-step run on the same backend meanwhile raises :class:`EngineBusyError`.
    """
    n_slots = min(int(batch_size), model.n_envs)
    if n_slots <= 0:
        return
    if cost is None:
        cost = engine.estimate_cost(model, frames)
    if len(cost) != model.n_envs:
        raise ValueError(f"cost has {len(cost)} entries for {model.n_envs} runs")
    runs = _Runs(engine, frames)
    runs.add(model)
    engine.claim_slots(n_slots)
    try:
        queue = _Queue(queue_order(cost, order, QUEUE_WINDOW_PER_SLOT * n_slots))
        yield from _stream_runs(engine, runs, queue, frames, record_every, n_slots, min_chunk, counters)
    finally:
        engine.release_slots(n_slots)


def feed_runs(engine, feeder, frames: int, record_every: int, batch_size: int, min_chunk: int = 1,
              counters: SlotCounters | None = None) -> Iterator[tuple[int, RunRecord]]:
    """An open stream: yield ``(i, record)`` for runs that ``feeder`` hands in while others run.

    ``feeder(free)`` is called whenever slots are free and returns a :class:`Model` of new runs (more
    than ``free`` may come: the rest wait for slots) or None when none is ready yet; ``i`` counts fed runs
    from 0 in feed order. Slots take runs in feed order. The stream ends when the feeder has nothing
    while no run is in flight and every finished run was handed out (the caller feeds new runs when it
    gets results). A run's record is the one :func:`stream_runs` gives it, whatever else was fed.
    """
    n_slots = int(batch_size)
    if n_slots <= 0:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    runs = _Runs(engine, frames)
    engine.claim_slots(n_slots)
    try:
        yield from _stream_runs(engine, runs, _Feed(runs, feeder), frames, record_every, n_slots, min_chunk,
                                counters)
    finally:
        engine.release_slots(n_slots)


def _stream_runs(engine, runs: _Runs, source, frames: int, record_every: int, B: int, min_chunk: int,
                 counters: SlotCounters | None) -> Iterator[tuple[int, RunRecord]]:
    """The stream's loop over ``B`` (>= 1) claimed slots; ``source.take(n)`` gives up to ``n`` new run numbers."""
    scene, o = engine.scene, engine.scene.options
    backend = engine.backend(B)
    fresh = bool(getattr(backend, "reads_are_new", False))
    read_later = getattr(backend, "read_slots_later", None)
    counters = counters if counters is not None else SlotCounters()
    fps, dx = o.fps, o.dx
    frame_dt = 1.0 / fps
    lo, hi = 1.5 * dx, o.domain - 1.5 * dx
    n_settle = round(o.settle_seconds * fps)
    names = scene.kinematic_names
    nk = len(names)
    counts = np.array([max(b.count, 1) for b in scene.bodies], float)

    run = np.full(B, -1, np.int64)
    step = np.zeros(B, np.int64)            # frames done: settling ones first, then 0..frames-1
    cur_nsub = np.zeros(B, np.int64)
    cur_dt = np.zeros(B)
    off = np.zeros(B, np.int64)
    stats_prev = np.zeros((B, backend.nstats))
    imp_acc = np.zeros((B, max(nk, 1), 3))
    w_acc = np.zeros((B, max(nk, 1)))
    work = np.zeros((B, max(nk, 1)))
    last_force = np.zeros((B, max(nk, 1), 3))
    kin_slot: list[np.ndarray | None] = [None] * B
    records: list[RunRecord | None] = [None] * B
    started = np.zeros(B)
    kin_cache: dict[tuple[int, int], np.ndarray] = {}   # (frame, substeps) -> kinematic table (read only)
    pos_cache: dict[tuple[int, int], np.ndarray] = {}   # (frame, object) -> displacement

    def kin_table(frame: int, nsub: int) -> np.ndarray:
        key = (frame, nsub)   # runs with the same substeps share a frame's table
        if key not in kin_cache:
            if len(kin_cache) >= 4096:
                kin_cache.pop(next(iter(kin_cache)))
            kin_cache[key] = kinematic_table(scene, frame, np.array([nsub]), np.array([frame_dt / nsub]),
                                             np.ones(1, bool))[0]
        return kin_cache[key]

    def prefetch(ending: np.ndarray) -> None:
        """Build, while the GPU works, the kinematic tables that slots ``ending`` their frame in this chunk
        will most likely need next (their planned substeps; the velocity guard rarely raises them)."""
        for b in ending:
            nxt = int(step[b]) + 1 - n_settle   # the frame after this one (negative: still settling)
            if 0 <= nxt < frames:
                kin_table(nxt, int(runs.nsub[run[b]]))

    def begin_frame(b: int) -> str | None:
        settling = step[b] < n_settle
        frame = -1 - int(step[b]) if settling else int(step[b]) - n_settle
        i = run[b]
        vmax = float(stats_prev[b, STAT_VMAX])
        nsub = velocity_guard_one(int(runs.nsub[i]), vmax, dx, fps, o.velocity_cfl)
        reason = substep_failure(nsub, o.max_substeps_per_frame, frame, vmax)
        if reason:
            return reason
        if nsub > runs.nsub[i]:
            records[b].guard_frames += 1
        cur_nsub[b], cur_dt[b], off[b] = nsub, frame_dt / nsub, 0
        kin_slot[b] = np.zeros((nsub, max(nk, 1), 6)) if settling else kin_table(frame, nsub)
        return None

    def snapshot(group: list[int], frame_of: dict[int, int], recorded_of: dict[int, bool]) -> None:
        """Take what the records of slots ``group`` keep of the frame that just ended (particles read from the
        device, host copies of the slot's statistics and sums) before the next launch changes it; the
        records are written by :func:`write` while the GPU runs the next chunk."""
        host_of = {b: [r for r in scene.reductions if frame_of[b] % r.every == 0] for b in group}
        need = [b for b in group if recorded_of[b] or host_of[b]]
        reads: dict[int, tuple[Any, int]] = {}
        if need:
            if read_later is not None:   # the copy back may finish while the next chunk runs
                read = read_later(np.array(need))
            else:
                x, d = backend.read_slots(np.array(need))
                if not fresh:   # the backend reuses its read buffers
                    x, d = x.copy(), d.copy()
                read = ReadyRead((x, d))
            reads = {b: (read, j) for j, b in enumerate(need)}
        pending.extend((records[b], frame_of[b], stats_prev[b].copy(), last_force[b].copy(), work[b].copy(),
                        reads.get(b), host_of[b], recorded_of[b]) for b in group)

    def write() -> None:
        """Append the pending frames to their records (a run that failed since keeps no particle frames)."""
        for rec, frame, st, force, wk, read, reductions, recorded in pending:
            xb = None
            if read is not None:
                (x, d), j = read[0].result(), read[1]
                xb = (x[j:j + 1], d[j:j + 1])
            s = rec.series
            s.setdefault("max_speed", []).append(float(st[STAT_VMAX]))
            s.setdefault("kinetic_energy", []).append(float(st[STAT_KE]))
            for i, body in enumerate(scene.bodies):
                col = BODY0 + 4 * i
                s.setdefault(f"centroid/{body.name}", []).append(st[col:col + 3] / counts[i])
                s.setdefault(f"mean_damage/{body.name}", []).append(float(st[col + 3] / counts[i]))
            for c, (name, path) in enumerate(zip(names, scene.kinematic_paths, strict=True)):
                s.setdefault(f"force/{name}", []).append(force[c])   # a row of the snapshot's own copy
                s.setdefault(f"work/{name}", []).append(float(wk[c]))
                if (frame, c) not in pos_cache:
                    pos_cache[(frame, c)] = path.displacement(frame / fps)
                s.setdefault(f"position/{name}", []).append(pos_cache[(frame, c)].copy())
            for r in reductions:
                v = np.asarray(r.fn(*xb, scene), float).reshape(1, -1)[0]
                s.setdefault(r.name, []).append(float(v[0]) if v.size == 1 else v.copy())
            if recorded:
                if rec.failure is None:
                    rec.positions.append(xb[0][0])
                    rec.damage.append(xb[1][0])
                rec.frames.append(frame)
        pending.clear()

    def finish(b: int) -> tuple[int, RunRecord]:
        rec = records[b]
        rec.wall_time_s = (time.perf_counter() - started[b]) / B   # the run's share of the device
        if rec.failure is not None:
            rec.positions, rec.damage = [], []
        out = (int(run[b]), rec)
        run[b], records[b], kin_slot[b], cur_nsub[b] = -1, None, None, 0
        return out

    backend.kinematic_sums()   # start every slot's sums from zero (a warm backend may hold a previous batch's)
    # finished runs not yet handed out: they are yielded once the next chunk is launched, so that the
    # caller's work on them (features, stores) overlaps the GPU's instead of leaving it idle
    done: list[tuple[int, RunRecord]] = []
    # frames taken at a frame end, appended to their records after the next launch (snapshot, write)
    pending: list[tuple] = []
    while True:
        # refill empty slots from the queue (one device reset for all of them)
        empty = [b for b in range(B) if run[b] < 0]
        new = list(zip(empty, source.take(len(empty)), strict=False))
        if new:
            slots = np.array([b for b, _ in new])
            idx = np.array([i for _, i in new])
            backend.load_slots(slots, runs.table[idx], runs.fric[idx])
            init_stats = backend.frame_stats(lo, hi, slots) if n_settle == 0 else None
            for b, i in new:
                run[b], step[b], started[b] = i, 0, time.perf_counter()
                records[b] = RunRecord(dt=float(runs.dt[i]))
                stats_prev[b] = init_stats[b] if init_stats is not None else 0.0
                work[b] = imp_acc[b] = w_acc[b] = last_force[b] = 0.0
                if n_settle == 0:
                    snapshot([b], {b: 0}, {b: True})
                reason = begin_frame(b) if frames + n_settle > 0 else None
                if reason:
                    records[b].failure = reason
                if reason or frames + n_settle == 0:
                    done.append(finish(b))
        active = run >= 0
        if not active.any():
            write()
            handed = bool(done)
            yield from done
            done = []
            if handed:
                continue   # new runs failed at once, or the caller may feed more after these: refill again
            return
        rem = np.where(active, cur_nsub - off, 0)
        K = int(max(rem[active].min(), min(int(min_chunk), rem.max())))
        n_chunk = np.minimum(rem, K)
        cap = 1 << max(K - 1, 0).bit_length()
        kin = np.zeros((B, cap, max(nk, 1), 6))
        for b in np.flatnonzero(active):
            kin[b, :n_chunk[b]] = kin_slot[b][off[b]:off[b] + n_chunk[b]]
        settling = active & (step < n_settle)
        backend.set_frame(np.where(active, cur_dt, frame_dt), n_chunk, kin, damage_on=~settling,
                          damping=np.where(settling, o.settle_damping, 0.0))
        backend.advance(K)   # asynchronous on a GPU: the host goes on while the chunk runs
        write()
        yield from done
        done = []
        counters.useful += int(n_chunk.sum())
        counters.launched += B * K
        counters.chunks += 1
        off += n_chunk
        ending = np.flatnonzero(active & (off >= cur_nsub))
        prefetch(ending)
        ended = [int(b) for b in ending]
        if not ended:
            continue
        # a slot's force/work sums stay on the device for its whole frame (float32, as in lock-step)
        stats, imp, w = backend.frame_end(lo, hi, ending)
        imp_acc[ending, :nk] = imp
        w_acc[ending, :nk] = w
        # what the host does between this sync and the next launch leaves the GPU idle: the slots' bookkeeping
        # is done for all of them at once, and a message is built only for a run that looks unhealthy
        ends = stats[ending]
        extra = imp_acc[ending, :nk].reshape(len(ending), -1).sum(axis=1) + w_acc[ending, :nk].sum(axis=1)
        suspect = unhealthy(ends, runs.bound[run[ending]], extra)
        stats_prev[ending] = ends
        last_force[ending] = imp_acc[ending] * fps
        was_settling_all = step[ending] < n_settle
        framing = ending[~was_settling_all]
        work[framing] += w_acc[framing]
        imp_acc[ending] = 0.0
        w_acc[ending] = 0.0
        group, frame_of, recorded_of = [], {}, {}
        for j, b in enumerate(ended):
            rec = records[b]
            was_settling = bool(was_settling_all[j])
            frame = -1 - int(step[b]) if was_settling else int(step[b]) - n_settle
            if was_settling:
                rec.settle_substeps += int(cur_nsub[b])
            else:
                rec.substeps += int(cur_nsub[b])
            reason = frame_failure(ends[j], float(runs.bound[run[b]]), frame + 1, float(extra[j])) \
                if suspect[j] else None   # unhealthy() flags exactly the rows frame_failure fails
            if reason:
                rec.failure = reason
                done.append(finish(b))
                continue
            step[b] += 1
            if step[b] == n_settle or not was_settling:
                f = 0 if was_settling else frame + 1
                group.append(b)
                frame_of[b] = f
                recorded_of[b] = was_settling or f % record_every == 0 or f == frames
        if group:
            snapshot(group, frame_of, recorded_of)
        for b in ended:
            if run[b] < 0:
                continue
            if step[b] == n_settle + frames:
                done.append(finish(b))
                continue
            reason = begin_frame(b)
            if reason:
                records[b].failure = reason
                done.append(finish(b))


__all__ = ["QUEUE_ORDERS", "EngineBusyError", "SlotCounters", "feed_runs", "queue_order", "stream_runs"]
