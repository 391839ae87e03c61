"""Answering many targets in worker processes: :meth:`Inverter.invert_many` with ``workers=N``.

Each worker loads the same bundle once and answers contiguous slices of the targets; the slices come back in
order. Every answer depends on its target, the method and the seed only (never on the other targets, the
batch or the order), so the answers are those of one process, bit for bit; only the per-target timings
differ. Workers start with ``spawn`` (a forked torch is not safe) and each pays the bundle's load and its
first answer (a few seconds), so processes pay off for hundreds of targets, not a handful. Each worker runs its
native thread pools (BLAS, OpenMP, torch) on the inverter's ``threads`` (default one) for its whole life: left
at one thread per core, sixteen workers on a 16-core host answered 3x slower than one process.
"""

from __future__ import annotations

import logging
import multiprocessing
import warnings
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError
from invphys.core.threads import limit_threads
from invphys.core.user_targets import UserTargets

#: slices per worker: a few each, so a worker that drew slow targets does not hold the others up
SLICES_PER_WORKER = 4
#: most worker processes
MAX_WORKERS = 256

_INVERTER: Any = None


def check_workers(workers: Any) -> int:
    """``workers`` as a count (0 or 1: this process), or one line."""
    if not is_count(workers, 0, MAX_WORKERS):
        raise InvphysError(f"workers must be a whole number in 0 .. {MAX_WORKERS}, got {workers!r}")
    return int(workers)


def slices(n: int, workers: int) -> list[np.ndarray]:
    """Rows ``0..n-1`` cut into contiguous slices, about :data:`SLICES_PER_WORKER` per worker."""
    k = max(1, min(n, workers * SLICES_PER_WORKER))
    return [s for s in np.array_split(np.arange(n), k) if len(s)]


def answer_in_processes(inv: Any, t: UserTargets, workers: int, options: dict[str, Any],
                        loader: Callable[..., Any], on_answer: Callable[[int], None] | None = None) -> list[Any]:
    """``inv.invert_many(t, **options)`` answered by ``workers`` processes, results in target order; each
    process loads the bundle with ``loader`` (``load_inverter``, handed in by reference); ``on_answer(n)`` as
    a slice of ``n`` targets comes back. The processes stay up for the inverter's later calls with as many
    workers (their start is paid once)."""
    if inv.bundle._registry is not None and not _default_registry(inv.bundle._registry):
        raise InvphysError("workers: this bundle was loaded with a registry of its own; worker processes "
                           "load plugins from installed entry points only (answer with workers=0)")
    pool = _pool(inv, workers, loader)
    try:
        futures = [pool.submit(_answer, t.take(rows), options, inv.pool_settings, inv.threads)
                   for rows in slices(len(t), workers)]
        for done in as_completed(futures):
            if on_answer is not None:
                on_answer(len(done.result()))
        return [r for f in futures for r in f.result()]
    except BrokenProcessPool as exc:   # a worker died (killed, out of memory): the next call starts afresh
        close_workers(inv)   # the broken pool's queues and locks released now, not left to interpreter exit
        raise InvphysError(f"a worker process died while answering ({exc}); a script that asks for workers "
                           "needs 'if __name__ == \"__main__\":' around its work, else answer with fewer workers "
                           "or workers=0") from None


def _pool(inv: Any, workers: int, loader: Callable[..., Any]) -> ProcessPoolExecutor:
    """The inverter's worker processes (started with ``spawn``), kept while it asks for as many with as many
    threads."""
    kept = inv.__dict__.get("_answer_pool")
    if kept is not None and kept[0] == (workers, inv.threads):
        return kept[1]
    close_workers(inv)
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_load,
                               initargs=(loader, str(Path(inv.bundle.root).resolve()), inv.threads))
    inv.__dict__["_answer_pool"] = ((workers, inv.threads), pool)
    return pool


def close_workers(inv: Any) -> None:
    """Shut down the worker processes ``inv`` keeps (its next call with workers starts new ones)."""
    kept = inv.__dict__.pop("_answer_pool", None)
    if kept is not None:
        kept[1].shutdown(wait=True, cancel_futures=True)


def _default_registry(registry: Any) -> bool:
    from invphys import registry as reg

    return registry is reg.default_registry()


def _load(loader: Callable[..., Any], root: str, threads: int | None) -> None:
    """In a worker: native pools on ``threads`` threads, then the bundle loaded once (its checks were the
    parent's; their warnings are not repeated)."""
    global _INVERTER
    limit_threads(threads)
    logging.getLogger("invphys").setLevel(logging.ERROR)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _INVERTER = loader(root, strict=False)


def _answer(t: UserTargets, options: dict[str, Any], pool_settings: Any, threads: int | None) -> list[Any]:
    _INVERTER.pool_settings, _INVERTER.threads = pool_settings, threads
    return list(_INVERTER.invert_many(t, workers=0, **options))


__all__ = ["MAX_WORKERS", "answer_in_processes", "check_workers", "close_workers", "slices"]
