"""Feature extraction in worker processes, off the thread that drives the simulator.

A GPU simulator hands each finished run to the host between launches; extracting its features there
(~0.14 s per paper-preset orange-peel run on one core of the H100 host) leaves the GPU idle meanwhile,
and threads do not help (the extractor's KD-trees hold the GIL). :class:`ExtractionPool` sends each
trajectory to one of ``workers`` processes (started with ``spawn``, so a CUDA context or a Taichi
runtime of the parent is never forked) and returns at once; the caller collects the features later.
Each worker builds the extractor once: from its ``{"type": ..., **config}`` block through the registry,
or unpickles the extractor instance it was given.

A trajectory whose arrays hold at least ``min_shared_bytes`` travels through shared memory
(:mod:`._shared_blocks`): a stager thread copies its arrays into a reusable block (the GIL released) and
sends the worker only the pickle of the rest, so neither the caller nor the pool's feeder thread spends
GIL-held time copying 20 MB per run; without a free block it is pickled as before.

A worker that dies (the extractor crashed in native code, or the process was killed, e.g. for memory)
breaks a process pool and fails every run it held. The pool is replaced for the runs still to come, and
each run the broken pool held is retried alone in a fresh process: the runs that did not kill it keep
their features, and the one that did fails alone (:class:`ExtractionWorkerDied`, a recorded failure).
Processes that cannot build the extractor, or die before they have, are no run's fault: an
:class:`InvphysError` stops the caller.

A run whose extraction takes longer than ``timeout_s`` (default :data:`DEFAULT_TIMEOUT_S`: an extractor
stuck in a loop, a lock or native code) is stopped where it runs: each worker arms a timer
(``SIGALRM``, whose default action ends the process even inside native code) when it starts a run and
disarms it when the run is done, so the clock counts that run's extraction only, never a process's start
or a queue. The process ends, which is handled as a worker that died: the pool is replaced and the runs
it held are retried alone; the stuck run, stopped again alone, is a recorded failure
(:class:`ExtractionTimedOut`). Platforms without ``setitimer`` (Windows) have no timeout.

Each worker runs its native thread pools (BLAS, OpenMP, torch) on ``threads`` threads (default
:data:`DEFAULT_THREADS`, one): left alone, each of ``workers`` processes would start one thread per core of
the host, and on a 16-core GPU host six workers' 96 threads starve the process that drives the simulator.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
import weakref
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError, SimulationFailed
from invphys.core.results import SimulationResult
from invphys.core.threads import limit_threads
from invphys.plugins.executors._deadline import ExtractionTimedOut

_LOG = logging.getLogger(__name__)

#: seconds one run's feature extraction may take in a worker process before it is stopped (a failure)
DEFAULT_TIMEOUT_S = 600.0
#: native (BLAS / OpenMP / torch) threads per extraction worker process
DEFAULT_THREADS = 1
_WORKER_EXTRACTOR: Any = None
_WORKER_INIT_ERROR: InvphysError | None = None   # why this worker could not build the extractor
_WORKER_TIMEOUT_S: float | None = None

_CANNOT_BUILD = ("the feature-extraction processes cannot build the extractor ({}); a plugin registered by hand in "
                 "this process is not seen there (name it 'module:Class' or by an entry point), or set "
                 "extract_workers: 0 to extract in this process")


def _init_worker(extractor: Any, timeout_s: float | None = None, threads: int | None = DEFAULT_THREADS) -> None:
    """Build the worker's extractor; a failure is kept and raised for each run (a raising initializer would
    break the pool, which then reads as a worker that died). ``SIGALRM`` ends the process (the timeout).
    Native thread pools get ``threads`` threads before the extractor is built."""
    global _WORKER_EXTRACTOR, _WORKER_INIT_ERROR, _WORKER_TIMEOUT_S
    limit_threads(threads)
    if timeout_s is not None and hasattr(signal, "setitimer"):
        signal.signal(signal.SIGALRM, signal.SIG_DFL)
        _WORKER_TIMEOUT_S = timeout_s
    try:
        if isinstance(extractor, dict):
            from invphys import registry

            extractor = registry.create("feature_extractor", dict(extractor))
        _WORKER_EXTRACTOR = extractor
    except Exception as exc:
        _WORKER_INIT_ERROR = InvphysError(_CANNOT_BUILD.format(f"{type(exc).__name__}: {exc}"))


def _ready() -> None:
    """Nothing, in a worker that has built its extractor (else that worker's error)."""
    if _WORKER_INIT_ERROR is not None:
        raise _WORKER_INIT_ERROR


@contextlib.contextmanager
def _deadline() -> Any:
    """In a worker: the process ends (``SIGALRM``) unless the block is done within ``_WORKER_TIMEOUT_S``."""
    if _WORKER_TIMEOUT_S is None:
        yield
        return
    signal.setitimer(signal.ITIMER_REAL, _WORKER_TIMEOUT_S)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)


def _extract(trajectory: Any) -> np.ndarray:
    _ready()
    with _deadline():
        return np.asarray(_WORKER_EXTRACTOR.extract(trajectory), dtype=np.float64)


def _extract_shared(data: bytes, name: str, spans: list[tuple[int, int]]) -> np.ndarray:
    from invphys.plugins.executors._shared_blocks import unpack

    # the trajectory's arrays are views of the block: dropped on return, before the parent reuses the block
    return _extract(unpack(data, name, spans))


class ExtractionWorkerDied(SimulationFailed):
    """The process extracting one run's features died, also when the run was retried alone in a fresh one:
    the extractor crashes on it (or the process keeps being killed, e.g. for memory). That run's failure."""


def _settle(outer: Future, result: Any = None, exc: BaseException | None = None) -> None:
    """Give ``outer`` a result or an exception, unless it is already done (cancelled meanwhile)."""
    try:
        if exc is not None:
            outer.set_exception(exc)
        else:
            outer.set_result(result)
    except InvalidStateError:
        pass


def _chain(inner: Future, outer: Future) -> None:
    """Give ``outer`` the worker future ``inner``'s outcome."""
    if inner.cancelled():
        _settle(outer, exc=RuntimeError("feature extraction was cancelled"))
    elif inner.exception() is not None:
        _settle(outer, exc=inner.exception())
    else:
        _settle(outer, inner.result())


class ExtractionPool:
    """``workers`` processes extracting features with ``extractor`` (a plugin block or an instance), each on
    ``threads`` native threads (None: the libraries' defaults, one per core)."""

    def __init__(self, extractor: Any, workers: int, min_shared_bytes: int | None = 1 << 20,
                 timeout_s: float | None = DEFAULT_TIMEOUT_S, threads: int | None = DEFAULT_THREADS) -> None:
        import multiprocessing

        if workers < 1:
            raise InvphysError(f"extract_workers must be >= 1 for a pool, got {workers}")
        if timeout_s is not None and not timeout_s > 0:
            raise InvphysError(f"the extraction timeout must be > 0 seconds (or none), got {timeout_s}")
        if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
            raise InvphysError(f"extraction threads must be a whole number >= 1 (or none), got {threads!r}")
        self.workers = int(workers)
        #: native threads per worker process (None: the libraries' defaults)
        self.threads = threads
        #: seconds one run's extraction may take in a worker (None: no limit); see the module's text
        self.timeout_s = None if timeout_s is None else float(timeout_s)
        #: runs stopped for taking longer than ``timeout_s``
        self.timed_out = 0
        self._pool_kwargs: dict[str, Any] = dict(
            mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker,
            initargs=(dict(extractor) if isinstance(extractor, dict) else extractor, self.timeout_s, threads))
        self._pool = ProcessPoolExecutor(self.workers, **self._pool_kwargs)
        self._pool_lock = threading.Lock()
        # runs a broken pool held, retried one at a time, each alone in a fresh process (no thread until used)
        self._isolator = ThreadPoolExecutor(1, thread_name_prefix="extract-isolator")
        #: pools replaced after a worker died, and runs retried alone since
        self.renewed, self.retried = 0, 0
        self._cannot_start: InvphysError | None = None   # a fresh process died before building the extractor
        #: trajectories with at least this many bytes of arrays go through shared memory (None: never)
        self.min_shared_bytes = min_shared_bytes
        self._blocks: Any = None
        self._stager: ThreadPoolExecutor | None = None
        if min_shared_bytes is not None:
            from invphys.plugins.executors._shared_blocks import SharedBlocks

            # one block per run being extracted or queued for a worker, plus one being filled
            self._blocks = SharedBlocks(max_blocks=2 * self.workers + 2)
            self._stager = ThreadPoolExecutor(1, thread_name_prefix="extract-stager")
            # a pool kept for the process's life (the validator's) is never closed: unlink its blocks at exit
            weakref.finalize(self, self._blocks.close)

    def submit(self, res: SimulationResult) -> Future | None:
        """Start extracting an ok result's features (its trajectory is dropped here); None when there is
        nothing to extract (a failed run, or features already set)."""
        if not res.ok or res.features is not None:
            res.trajectory = None
            return None
        if res.trajectory is None:
            res.ok, res.failure = False, "feature extraction: the simulator returned no trajectory"
            return None
        fut = self.extract(res.trajectory)
        res.trajectory = None
        return fut

    def extract(self, trajectory: Any) -> Future:
        """Extract one trajectory's features in a worker (the future raises what the extractor raised).
        Returns at once: with shared memory on, a stager thread packs the trajectory and submits it."""
        if self._stager is None:
            return self._run(_extract, trajectory)
        outer: Future = Future()
        self._stager.submit(self._stage, trajectory, outer)
        return outer

    def _stage(self, trajectory: Any, outer: Future) -> None:
        """In the stager thread: pack ``trajectory`` into a block (or pickle it, without a free block) and
        chain the worker's future into ``outer``; the block is given back once the worker is done."""
        from invphys.plugins.executors._shared_blocks import pack

        if not outer.set_running_or_notify_cancel():   # cancelled while queued for the stager
            return
        try:
            packed = pack(trajectory, self._blocks, int(self.min_shared_bytes or 0))
            if packed is None:
                inner = self._run(_extract, trajectory)
            else:
                data, block, spans = packed
                try:
                    inner = self._run(_extract_shared, data, block.name, spans)
                except Exception:
                    self._blocks.release(block)
                    raise
                inner.add_done_callback(lambda _f, block=block: self._blocks.release(block))
        except Exception as exc:  # the caller's future carries it (resolve records it as the run's failure)
            outer.set_exception(exc)
            return
        inner.add_done_callback(lambda f: _chain(f, outer))

    def _run(self, fn: Callable[..., np.ndarray], *args: Any) -> Future:
        """``fn(*args)`` in a worker, as a future that outlives the worker's death (see the module's text);
        cancelling it cancels the work if no worker has taken it yet."""
        outer: Future = Future()
        with self._pool_lock:
            try:
                inner = self._pool.submit(fn, *args)
            except BrokenProcessPool:   # a worker died: a fresh pool for this run and those after it
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = ProcessPoolExecutor(self.workers, **self._pool_kwargs)
                self.renewed += 1
                inner = self._pool.submit(fn, *args)
        outer.add_done_callback(lambda o: inner.cancel() if o.cancelled() else None)
        inner.add_done_callback(lambda f: self._done(f, fn, args, outer))
        return outer

    def _done(self, inner: Future, fn: Callable[..., np.ndarray], args: tuple, outer: Future) -> None:
        """In the pool's thread: chain ``inner``'s outcome into ``outer``, or queue the run to be retried
        alone when the pool broke under it (without taking ``_pool_lock``: a submitter may hold it)."""
        if inner.cancelled() or not isinstance(inner.exception(), BrokenProcessPool):
            _chain(inner, outer)
            return
        try:
            self._isolator.submit(self._alone, fn, args, outer)
        except RuntimeError as exc:   # the pool is closing: nothing retries any more
            _settle(outer, exc=exc)

    def _alone(self, fn: Callable[..., np.ndarray], args: tuple, outer: Future) -> None:
        """Retry a run alone in a fresh one-worker process: its features, or its own failure if it dies.
        A process that dies before it has built its extractor is no run's fault: that stops the caller."""
        if outer.done():
            return
        if self._cannot_start is not None:
            _settle(outer, exc=self._cannot_start)
            return
        self.retried += 1
        if self.retried == 1:
            _LOG.warning("a feature-extraction worker process died; the pool was restarted and each run it held "
                         "is retried alone in a fresh process")
        try:
            with ProcessPoolExecutor(1, **self._pool_kwargs) as solo:
                try:
                    solo.submit(_ready).result()   # raises the process's own error if it cannot build one
                except BrokenProcessPool as exc:
                    self._cannot_start = InvphysError(_CANNOT_BUILD.format(f"a fresh process died starting: {exc}"))
                    _settle(outer, exc=self._cannot_start)
                    return
                procs = list((getattr(solo, "_processes", None) or {}).values())
                began = time.monotonic()
                try:
                    result = solo.submit(fn, *args).result()
                except BrokenProcessPool:
                    if self._alarmed(procs, time.monotonic() - began):
                        self.timed_out += 1
                        _settle(outer, exc=ExtractionTimedOut(
                            f"feature extraction took longer than {self.timeout_s:g} s (the extraction "
                            "timeout), also when retried alone in a fresh process; its process was stopped"))
                        return
                    raise
        except BrokenProcessPool:
            _settle(outer, exc=ExtractionWorkerDied(
                "the feature-extraction process died on this run, also when retried alone in a fresh process "
                "(the extractor crashed on it, or the process was killed, e.g. for memory)"))
        except BaseException as exc:
            _settle(outer, exc=exc)
        else:
            _settle(outer, result)

    def _alarmed(self, procs: list[Any], elapsed: float) -> bool:
        """Whether the process that ran a run alone (``procs``) was ended by its extraction timer: its exit
        status says so, or it died no sooner than the timeout after the run was handed to it."""
        if self.timeout_s is None or not hasattr(signal, "SIGALRM"):
            return False
        if elapsed >= self.timeout_s:
            return True
        for proc in procs:
            proc.join(timeout=10)
        return any(proc.exitcode == -signal.SIGALRM for proc in procs)

    @staticmethod
    def resolve(res: SimulationResult, fut: Future | None) -> SimulationResult:
        """Wait for ``fut`` and set ``res.features`` (or record the failure as the in-process path does;
        an :class:`InvphysError`, the user's to fix, propagates)."""
        if fut is None:
            return res
        from invphys.core.dataset import failure_reason

        try:
            res.features = fut.result()
        except InvphysError:
            raise
        except Exception as exc:  # the extractor raised, or its worker process died
            res.ok, res.failure = False, f"feature extraction: {failure_reason(exc)}"
        return res

    def close(self) -> None:
        if self._stager is not None:
            self._stager.shutdown(wait=True)  # every trajectory handed over reaches the pool (or fails there)
        with self._pool_lock:
            pool = self._pool
        pool.shutdown(wait=True, cancel_futures=True)
        self._isolator.shutdown(wait=True)   # retries already queued finish: their runs' features are kept
        if self._blocks is not None:
            self._blocks.close()

    def __enter__(self) -> ExtractionPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
