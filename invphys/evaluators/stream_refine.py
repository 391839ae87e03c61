"""Refine many targets on the simulator through one open stream: generations overlap across targets.

Each target runs its own search: first its start points (those not simulated yet; starts whose features
are known cost no run), then a strategy's ask/tell search from its best start (CMA-ES in [0, 1]^d seeded
per target, :func:`cma_strategy`; or the corrected surrogate, :mod:`~invphys.evaluators.corrected_refine`). A target's next generation is asked as soon as its
own runs are back, and its rows join the stream (:meth:`Simulator.simulate_feed`) while other targets'
runs are still in flight, so no generation waits for another target's slow run. A generation is told in
the order of its asks, never of completion: the answers do not depend on completion order, batch size
or the other targets. :class:`RunLog` records every finished run (target id, run number, point,
features, seconds, device); a re-run replays the logged runs and simulates only the rest. With ``stop``, a
target asks for no more runs once its best score reaches it (decided before each of its generations, from
its own told runs only: a stopped target's runs are the first runs of the same target without a stop).
With ``patience`` P > 0 and ``min_gain`` G, a target also stops once it stalls (:func:`stalled`): before a
generation, with n told runs (its simulated starts included), n >= P and best(n) - best(n - P) < G, where
best(k) is its best score after its first k told runs (best(0): its starts known at no run; no score yet:
-inf, and -inf to -inf is no gain). The same prefix property holds, and ``TargetRefine.batches`` records
the sizes of its told generations, so a replay of the per-run bests knows the decision points exactly.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError
from invphys.evaluators.refine_log import RunLog


@dataclass
class TargetRefine:
    """One target's refine: its id, target features, starts and their known features (NaN rows: to
    simulate), and the outcome (best point, score, features, every point simulated, runs, seconds)."""

    tid: str
    target: np.ndarray
    starts: np.ndarray
    known: np.ndarray
    seed: int
    theta: np.ndarray | None = None
    score: float = -np.inf
    features: np.ndarray | None = None
    best_index: int = -1           # index into ``points`` of the answer
    points: list[tuple[np.ndarray, float, np.ndarray]] = field(default_factory=list)
    runs: int = 0                  # simulator runs spent (replayed ones included)
    replayed: int = 0
    seconds: float = 0.0
    start_scores: np.ndarray | None = None
    stopped: bool = False          # it reached the stop score with runs left
    stalled: bool = False          # it stopped with runs left because its best gained < min_gain in patience runs
    costs: list[float] = field(default_factory=list)   # each asked run's estimated cost (with a RunCost), in ask order
    capped: bool = False           # its cost budget cut a generation short: it asks no more runs
    batches: list[int] = field(default_factory=list)   # the sizes of its told generations (starts first), in order
    bests: list[float] = field(default_factory=list)   # best score after 0, 1, 2, ... told runs
    ask_s: float = 0.0             # seconds its search spent proposing and being told (wall, between runs)
    ask_cpu_s: float = 0.0         # the same blocks' CPU seconds of the thread running them (ask_s >> it: waited)
    back_s: list[float] = field(default_factory=list)  # seconds into the refine when each generation was all back

    @property
    def cost(self) -> float:
        """The estimated cost of its asked runs, in typical runs (0 without a :class:`RunCost`)."""
        return math.fsum(self.costs)


_GLOBAL_RANDOM = threading.RLock()   # NumPy's global random state, swapped by CMASearch


class CMASearch:
    """The ``cma`` strategy: ask/tell CMA-ES in [0, 1]^d from the target's best start (step ``sigma0``,
    ``popsize`` points per generation, restarts), with a NumPy random state of its own."""

    def __init__(self, t: TargetRefine, popsize: int, sigma0: float, left: int) -> None:
        self.t, self.d = t, t.starts.shape[1]
        self._random: Any = None
        with self.own_random():
            from invphys.core.spaces import raw_space
            from invphys.plugins.optimizers.cma_es import CMAES

            cma = CMAES(popsize=popsize, sigma0=sigma0, budget=left, restarts=True)
            self.cma = cma.ask_tell(raw_space(self.d), t.seed, t.theta, left)

    def ask(self, left: int) -> np.ndarray:
        with self.own_random():
            pts = self.cma.ask() if not self.cma.done else np.empty((0, self.d))
        return np.asarray(pts, float).reshape(-1, self.d)[:left]

    def tell(self, points: np.ndarray, ys: np.ndarray, scores: np.ndarray, before: float) -> None:
        with self.own_random():
            self.cma.tell(points, scores)

    @contextmanager
    def own_random(self) -> Iterator[None]:
        """The ``cma`` package draws from NumPy's global random state: each search gets a state of its own, so
        the searches' draws do not depend on the order in which targets ask (one search at a time: they may
        ask in background threads)."""
        with _GLOBAL_RANDOM:
            yield from self._swapped()

    def _swapped(self) -> Iterator[None]:
        outer = np.random.get_state()
        np.random.set_state(self._random if self._random is not None else
                            np.random.RandomState(self.t.seed % (2**32)).get_state())
        try:
            yield
        finally:
            self._random = np.random.get_state()
            np.random.set_state(outer)


@dataclass(frozen=True)
class RunCost:
    """A cost budget per target: ``of(points (k, d) normalised) -> (k,)`` each run's estimated cost (in
    typical runs: 1.0 is an average run of the parameter box) and ``budget``, the most a target may spend
    (``inf``: costs recorded, never capped).
    Costs are estimated from the parameters alone, so where a target stops does not depend on timing."""

    of: Callable[[np.ndarray], np.ndarray]
    budget: float


def affordable(spent: float, costs: np.ndarray, budget: float) -> int:
    """How many leading runs of ``costs`` (each >= 0) fit a cost ``budget`` of which ``spent`` is gone (a
    relative 1e-12 of slack, so a budget met exactly by rounded sums still fits)."""
    return int(np.sum(spent + np.cumsum(costs) <= budget * (1 + 1e-12)))


#: ``strategy(target, runs left) -> search`` with ``ask(left) -> (k, d)`` and ``tell(points, features,
#: scores, best score before)``; made once a target's starts are in (its best start in ``target.theta``)
Strategy = Callable[[TargetRefine, int], Any]


def cma_strategy(popsize: int = 8, sigma0: float = 0.012) -> Strategy:
    """The ``cma`` strategy's factory."""
    return lambda t, left: CMASearch(t, popsize, sigma0, left)


class _Search:
    """A target's state: the generation in flight (asked points and their results by ask order)."""

    def __init__(self, t: TargetRefine, budget: int, popsize: int, sigma0: float, d: int,
                 strategy: Strategy | None = None, stop: float | None = None, patience: int = 0,
                 min_gain: float = 0.0, cost: RunCost | None = None) -> None:
        self.t, self.budget, self.d, self.stop = t, budget, d, stop
        self.patience, self.min_gain, self.cost = patience, min_gain, cost
        self.strategy = strategy or cma_strategy(popsize, sigma0)
        self.search: Any = None
        self.asked = np.empty((0, d))
        self.results: list[tuple[np.ndarray, float, str, bool] | None] = []
        self.phase = "starts"
        self.before = -np.inf

    def next_points(self) -> np.ndarray:
        """The next generation (empty: the target is finished)."""
        left = self.budget - self.t.runs
        if self.phase == "starts":
            todo = ~np.all(np.isfinite(self.t.known), axis=1)
            return self._afford(self.t.starts[todo][:max(left, 0)])
        if left <= 0 or self.t.capped:
            return np.empty((0, self.d))
        if self.stop is not None and self.t.score >= self.stop:   # reached: no more runs
            self.t.stopped = True
            return np.empty((0, self.d))
        if stalled(self.t.bests, self.patience, self.min_gain):
            self.t.stalled = True
            return np.empty((0, self.d))
        t0, c0 = time.perf_counter(), time.thread_time()
        if self.search is None:
            self.search = self.strategy(self.t, left)
        self.before = self.t.score
        pts = self.search.ask(left)
        self.t.ask_s += time.perf_counter() - t0
        self.t.ask_cpu_s += time.thread_time() - c0
        return self._afford(np.clip(np.asarray(pts, float).reshape(-1, self.d)[:left], 0.0, 1.0))

    def _afford(self, pts: np.ndarray) -> np.ndarray:
        """The longest head of ``pts`` whose estimated cost fits what is left of the target's cost budget
        (all of them without one); a cut marks the target ``capped``."""
        if self.cost is None or not len(pts):
            return pts
        c = np.asarray(self.cost.of(pts), float).reshape(len(pts))
        keep = affordable(self.t.cost, c, self.cost.budget)
        if keep < len(pts):
            self.t.capped = True
        self.t.costs += c[:keep].tolist()
        return pts[:keep]

    def tell(self, ys: np.ndarray, scores: np.ndarray) -> None:
        if self.search is not None:
            t0, c0 = time.perf_counter(), time.thread_time()
            self.search.tell(self.asked, ys, scores, self.before)
            self.t.ask_s += time.perf_counter() - t0
            self.t.ask_cpu_s += time.thread_time() - c0


def stream_refine(targets: list[TargetRefine], simulate: Callable[[Callable[[int], np.ndarray | None]],
                                                                 Iterator[tuple[int, np.ndarray, float, str]]],
                  score: Callable[[np.ndarray, np.ndarray], np.ndarray], budget: int, popsize: int = 8,
                  sigma0: float = 0.012, log: RunLog | None = None,
                  on_run: Callable[[int, bool], None] | None = None,
                  strategy: Strategy | None = None, stop: float | None = None, ask_workers: int = 1,
                  stats: dict[str, float] | None = None, patience: int | None = 0,
                  min_gain: float = 0.0, cost: RunCost | None = None) -> list[TargetRefine]:
    """Refine every target with ``budget`` simulator runs (its unsimulated starts included), one open stream.

    ``simulate(feeder)`` yields ``(i, features (M,) or NaN, seconds, device)`` for the rows (normalised,
    (k, d)) that ``feeder(free)`` hands it, ``i`` counting fed rows from 0 (e.g. through
    :meth:`Simulator.simulate_feed`). ``score(features (B, M), targets (B, M)) -> (B,)``. Each target's
    answer is its best simulated point, starts included. ``on_run(runs, replayed)`` reports progress.
    ``strategy`` searches after the starts (default: :func:`cma_strategy` with ``popsize`` and ``sigma0``).
    ``stop``: a target whose best score (its starts included) reaches it asks for no further generation
    (None, or outside (0, 1): never; the starts are always simulated). ``patience`` (runs; 0 or None: off) and
    ``min_gain``: a target asks no further generation once it stalls (:func:`stalled`), again from its own
    told runs only, so its runs are a prefix of the same target's without the rule. ``cost``
    (:class:`RunCost`): a generation (its starts too) is cut to the longest head whose estimated cost fits the
    target's cost budget, and a cut target asks no more: again a prefix of the same target's runs without it.
    ``ask_workers``: threads that tell a target its generation and ask its next one while the simulator
    goes on (0: in the stream's own loop, between launches); the feeder hands out whatever rows are ready
    and waits for an ask only when no row is in flight. The answers are the same for any number.
    ``stats["ask_wait_s"]`` gets the seconds the stream waited for an ask with no row in flight (with 0
    workers: every ask's seconds, as each holds the stream).
    """
    if budget < 0 or popsize < 2 or not sigma0 > 0:
        raise InvphysError(f"refine: budget >= 0, popsize >= 2 and sigma0 > 0 needed, got {budget}, {popsize}, "
                           f"{sigma0}")
    if not is_count(ask_workers, 0, 64):
        raise InvphysError(f"refine: ask workers must be a whole number in 0 .. 64, got {ask_workers!r}")
    patience, min_gain = check_stall(patience, min_gain)
    d = targets[0].starts.shape[1] if targets else 0
    stop = stop if stop is not None and 0.0 < stop < 1.0 else None
    searches = [_Search(t, budget, popsize, sigma0, d, strategy, stop, patience, min_gain, cost) for t in targets]
    asks = _Asks(searches, log, score, on_run or (lambda _n, _r: None), int(ask_workers))
    t_start = time.perf_counter()
    try:
        for k, s in enumerate(searches):
            _start_known(s, score)
            asks.submit(k)
        for i, y, seconds, device in simulate(asks.feeder):
            k, j = asks.fed[i]
            s = searches[k]
            if log is not None:
                log.add(s.t.tid, s.t.runs + j, s.asked[j], y, seconds, device)
            s.results[j] = (np.asarray(y, float), float(seconds), device, False)
            asks.back += 1
            if all(r is not None for r in s.results):
                s.t.back_s.append(time.perf_counter() - t_start)
                asks.submit(k)
        asks.drain()
    finally:
        asks.close()
    if stats is not None:
        stats["ask_wait_s"] = asks.wait_s if ask_workers else float(sum(t.ask_s for t in targets))
    if log is not None:
        log.save()
    if asks.queue or any(s.phase != "done" for s in searches):
        raise InvphysError("refine: the simulator stream ended before every asked run came back")
    return targets


def check_stall(patience: Any, min_gain: Any) -> tuple[int, float]:
    """``patience`` (a whole number of runs in 0 .. 100000; None: 0, off) and ``min_gain`` (an R_actual gain in
    [0, 1]) checked, else one error line."""
    patience = 0 if patience is None else patience
    if not is_count(patience, 0, 100_000):
        raise InvphysError(f"refine patience must be a whole number of runs in 0 .. 100000 (0: off), got {patience!r}")
    if not in_unit_interval(min_gain):
        raise InvphysError(f"refine min gain must be an R_actual gain in [0, 1], got {min_gain!r}")
    return int(patience), float(min_gain)


def in_unit_interval(value: Any) -> bool:
    """Whether ``value`` is a number (not a bool or a string) in [0, 1]."""
    try:
        return not isinstance(value, (bool, str)) and 0.0 <= float(value) <= 1.0
    except (TypeError, ValueError):
        return False


def stalled(bests: list[float], patience: int, min_gain: float) -> bool:
    """Whether a target whose best score after 0, 1, ..., n told runs is ``bests`` (n + 1 values) has stalled:
    ``patience`` P > 0, n >= P and best(n) - best(n - P) < ``min_gain`` (no change, -inf to -inf included, is
    a gain of 0)."""
    n = len(bests) - 1
    if patience <= 0 or n < patience:
        return False
    now, before = bests[n], bests[n - patience]
    return (0.0 if now == before else now - before) < min_gain


class _Asks:
    """The targets' tells and asks (in ``workers`` background threads, or inline with 0) and the rows they
    queue for the stream. A target has at most one job at a time (its generation's results are all in)."""

    def __init__(self, searches: list[_Search], log: RunLog | None,
                 score: Callable[[np.ndarray, np.ndarray], np.ndarray], note: Callable[[int, bool], None],
                 workers: int) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.searches, self.log, self.score, self.note = searches, log, score, note
        self.queue: list[tuple[int, int]] = []   # (search, member) rows waiting for a slot
        self.fed: list[tuple[int, int]] = []     # row i of the stream -> (search, member)
        self.back = 0                            # rows whose results came back
        self.jobs: list[Any] = []                # background jobs not yet collected
        self.wait_s = 0.0
        self._ready = threading.Condition()
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="refine-ask") if workers else None

    def submit(self, k: int) -> None:
        """Tell target ``k`` its generation (when one was asked) and ask its next one."""
        if self._pool is None:
            self._job(k)
            return
        self._collect()
        job = self._pool.submit(self._job, k)
        job.add_done_callback(lambda _f: self._wake())
        self.jobs.append(job)

    def _wake(self) -> None:
        with self._ready:
            self._ready.notify_all()

    def _job(self, k: int) -> None:
        s = self.searches[k]
        if s.results and all(r is not None for r in s.results) and s.phase != "done":
            _tell(s, self.score, self.note)
        rows = _advance(s, self.log, self.score, self.note)
        with self._ready:
            self.queue.extend((k, j) for j in rows)
            self._ready.notify_all()

    def _collect(self) -> None:
        """Drop finished jobs; raise what one raised."""
        done = [f for f in self.jobs if f.done()]
        self.jobs = [f for f in self.jobs if not f.done()]
        for f in done:
            f.result()

    def feeder(self, free: int) -> np.ndarray | None:
        """The queued rows; with none queued and none in flight, wait for the pending asks."""
        with self._ready:
            if not self.queue and self.back == len(self.fed) and self._pool is not None:
                t0 = time.perf_counter()
                while not self.queue and any(not f.done() for f in self.jobs):
                    self._ready.wait(0.05)
                self.wait_s += time.perf_counter() - t0
            self._collect()
            if not self.queue:
                return None
            rows, self.queue = self.queue, []
        self.fed.extend(rows)
        return np.array([self.searches[k].asked[j] for k, j in rows])

    def drain(self) -> None:
        for f in self.jobs:
            f.result()
        self.jobs = []

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)


def _advance(s: _Search, log: RunLog | None, score: Callable[[np.ndarray, np.ndarray], np.ndarray],
             note: Callable[[int, bool], None]) -> list[int]:
    """Ask ``s``'s next generation; replay what the log holds and return the members to simulate (repeat
    while the log answers whole generations; none: the target is done)."""
    while True:
        pts = s.next_points()
        if len(pts) == 0 and s.phase == "starts":
            _finish_starts(s)
            continue
        if len(pts) == 0:
            s.phase = "done"
            return []
        s.asked, s.results = pts, [None] * len(pts)
        todo = []
        for j, p in enumerate(pts):
            hit = log.get(s.t.tid, s.t.runs + j, p) if log is not None else None
            if hit is not None:
                s.results[j] = (hit[0], hit[1], hit[2], True)
            else:
                todo.append(j)
        if todo:
            return todo
        _tell(s, score, note)


def _start_known(s: _Search, score: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
    """Score and record the starts whose features are known already (the others: NaN start scores)."""
    t = s.t
    ok = np.all(np.isfinite(t.known), axis=1)
    sc = _scores(score, t.known, t.target)
    t.start_scores = np.where(ok, sc, np.nan)
    for j in np.flatnonzero(ok):
        _record(t, t.starts[j], float(sc[j]), t.known[j])
    t.bests = [float(t.score)]


def _tell(s: _Search, score: Callable[[np.ndarray, np.ndarray], np.ndarray],
          note: Callable[[int, bool], None]) -> None:
    """Every result of ``s``'s generation is in: tell them in ask order."""
    t = s.t
    ys = np.array([r[0] for r in s.results])  # type: ignore[index]
    sc = _scores(score, ys, t.target)
    for j, (p, r) in enumerate(zip(s.asked, s.results, strict=True)):
        assert r is not None
        t.runs += 1
        t.seconds += r[1]
        t.replayed += int(r[3])
        _record(t, p, float(sc[j]), ys[j])
        t.bests.append(float(t.score))
    t.batches.append(len(s.asked))
    note(len(s.asked), all(r[3] for r in s.results))  # type: ignore[index]
    if s.phase == "starts":
        todo = ~np.all(np.isfinite(t.known), axis=1)
        t.known = t.known.copy()
        t.known[np.flatnonzero(todo)[:len(ys)]] = ys
        assert t.start_scores is not None
        t.start_scores[np.flatnonzero(todo)[:len(ys)]] = np.where(np.isfinite(sc), sc, np.nan)
        _finish_starts(s)
    else:
        s.tell(ys, sc)


def _finish_starts(s: _Search) -> None:
    s.phase = "search"
    if s.t.theta is None:  # no start simulated successfully: search from the first start
        s.t.theta = s.t.starts[0].copy()


def _scores(score: Callable[[np.ndarray, np.ndarray], np.ndarray], y: np.ndarray, target: np.ndarray) -> np.ndarray:
    y = np.atleast_2d(np.asarray(y, float))
    if len(y) == 0:
        return np.zeros(0)
    ok = np.all(np.isfinite(y), axis=1)
    s = np.asarray(score(np.where(ok[:, None], y, 0.0), np.tile(target, (len(y), 1))), float)
    return np.where(ok & np.isfinite(s), s, -np.inf)


def _record(t: TargetRefine, theta: np.ndarray, score: float, y: np.ndarray) -> None:
    """A simulated point of target ``t``; it becomes the answer when strictly better (ties: the earlier)."""
    t.points.append((np.array(theta, float), score, np.array(y, float)))
    if t.theta is None or score > t.score:
        t.theta, t.score, t.features, t.best_index = np.array(theta, float), score, np.array(y, float), len(t.points) - 1


def feed_features(simulator: Any, extractor: Any, batch_size: int | None, pool: Any = None
                  ) -> Callable[[Callable[[int], np.ndarray | None]], Iterator[tuple[int, np.ndarray, float, str]]]:
    """``simulate`` for :func:`stream_refine`: normalised rows through ``simulator.simulate_feed``, features
    extracted as each run ends (NaN for a failed run or extraction), with the run's seconds and device.

    With ``pool`` (an :class:`~invphys.plugins.executors._extract_pool.ExtractionPool`) features are extracted
    in its worker processes while the simulator goes on, as dataset generation does, and each run is yielded
    once its features are back (out of finishing order: :func:`stream_refine` tells in ask order). A stream
    that runs dry while features are still being extracted is opened again for the rows their targets ask
    next, until a stream is given no rows."""
    space = simulator.parameter_space()
    m = len(extractor.feature_names)

    def run(feeder: Callable[[int], np.ndarray | None]) -> Iterator[tuple[int, np.ndarray, float, str]]:
        offset, fed = 0, [0]

        def physical(free: int) -> np.ndarray | None:
            rows = feeder(free)
            if rows is None or len(rows) == 0:
                return None
            fed[0] += len(rows)
            return space.denormalize(np.clip(rows, 0.0, 1.0))

        while True:
            fed[0] = 0
            pending: dict[int, tuple[Any, Any]] = {}
            for i, res in simulator.simulate_feed(physical, batch_size):
                if pool is None:
                    yield _fed_outcome(offset + i, res, extractor, m)
                    continue
                pending[offset + i] = (res, pool.submit(res))
                yield from _ready(pending, extractor, m, wait=False)
            yield from _ready(pending, extractor, m, wait=True)
            if pool is None or fed[0] == 0:
                return
            offset += fed[0]

    return run


def _ready(pending: dict[int, tuple[Any, Any]], extractor: Any, m: int, wait: bool
           ) -> Iterator[tuple[int, np.ndarray, float, str]]:
    """The pending runs whose features are back (``wait``: all of them, in feeding order)."""
    for i in sorted(i for i, (_, fut) in pending.items() if wait or fut is None or fut.done()):
        res, fut = pending.pop(i)
        yield _fed_outcome(i, res, extractor, m, fut)


def _fed_outcome(i: int, res: Any, extractor: Any, m: int, fut: Any = None) -> tuple[int, np.ndarray, float, str]:
    from invphys.plugins.validators.simulator import SimulatorValidator

    try:
        feats, _failure, stats = SimulatorValidator._outcome(res, extractor, m, fut)
    except InvphysError:
        raise
    except Exception:  # the extractor raised in a worker, or the worker died: a failed run
        feats, stats = None, getattr(res, "stats", None)
    y = np.full(m, np.nan) if feats is None else feats
    return i, y, float(stats.wall_time_s) if stats is not None else 0.0, str(stats.device) if stats is not None else ""


def timed(run: Callable[..., Iterator[Any]]) -> tuple[Callable[..., Iterator[Any]], dict[str, float]]:
    """``run`` wrapped to measure its wall time (``clock["wall_s"]``) while it yields."""
    clock = {"wall_s": 0.0}

    def wrapped(*args: Any) -> Iterator[Any]:
        t0 = time.perf_counter()
        try:
            yield from run(*args)
        finally:
            clock["wall_s"] += time.perf_counter() - t0

    return wrapped, clock


def log_key(parts: dict[str, Any]) -> str:
    """A short stable hash of ``parts`` (JSON)."""
    import hashlib

    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:24]
