"""The ``process`` executor: a pool of worker processes on this machine (spawn start method)."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import Executor, PluginConfig
from invphys.core.results import SimulationResult
from invphys.plugins.executors import _deadline
from invphys.plugins.executors._batch import batches, build_plugins, failed_result, run_batch
from invphys.plugins.executors._extract_pool import DEFAULT_TIMEOUT_S


def _init_worker(env: dict[str, str], gpus: list[int] | None = None, counter: object = None) -> None:
    os.environ.update(env)
    _deadline.DISPOSABLE = True   # an extraction stuck in native code may end this process (see _deadline)
    if gpus:
        with counter.get_lock():  # type: ignore[attr-defined]
            k = counter.value  # type: ignore[attr-defined]
            counter.value += 1  # type: ignore[attr-defined]
        os.environ["CUDA_VISIBLE_DEVICES"] = str(gpus[k % len(gpus)])


class ProcessExecutor(Executor):
    """Runs batches in a ``concurrent.futures`` process pool started with *spawn* (taichi and warp
    must not be initialised before a fork). Each worker rebuilds the simulator and extractor from
    their spec blocks once (so plugins must be importable there: installed entry points or
    ``module:Class`` paths) and keeps them for later batches.

    A run whose feature extraction takes longer than ``extract_timeout_s`` is interrupted in its worker
    and recorded as failed; an extractor stuck in native code ends its worker a little later (see
    :mod:`invphys.plugins.executors._deadline`), which is then handled as a worker that died.

    A worker process that dies (segfault, out of memory) breaks the pool: the pool is restarted and
    the batches it held are re-run one at a time (then row by row), so only the rows that kill a
    worker are stored as failed ("worker process died").

    With ``gpus`` each worker sees one GPU (``CUDA_VISIBLE_DEVICES``) and keeps its warm simulator for
    every batch it runs: several GPUs of one machine without Ray. A restarted pool numbers its workers
    afresh.
    """

    name = "process"

    class Config(PluginConfig):
        workers: int | None = Field(None, ge=1, description="worker processes (default: CPU count)")
        max_in_flight: int | None = Field(
            None, ge=1, description="batches submitted but not finished (default: 2 x workers)")
        threads_per_worker: int | None = Field(
            1, ge=1, description="OMP, MKL, OpenBLAS and taichi CPU threads per worker (None leaves the environment alone)")
        max_tasks_per_child: int | None = Field(
            None, ge=1, description="replace a worker after this many batches (bounds leaks)")
        isolate_failures: bool = Field(
            True, description="when a batch raises, re-run its rows one by one so only the bad row fails")
        gpus: list[int] | None = Field(
            None, description="one worker per GPU: worker k sees only GPU gpus[k] (CUDA_VISIBLE_DEVICES); "
                              "workers defaults to len(gpus)")
        extract_timeout_s: float | None = Field(
            DEFAULT_TIMEOUT_S, gt=0, description="seconds one run's feature extraction may take in a worker "
                                                 "before it is interrupted and the run recorded as failed "
                                                 "(null: no limit)")

    def _pool(self) -> Any:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        env: dict[str, str] = {}
        if self.config.threads_per_worker is not None:
            t = str(self.config.threads_per_worker)
            env = {"OMP_NUM_THREADS": t, "MKL_NUM_THREADS": t, "OPENBLAS_NUM_THREADS": t,
                   "TI_CPU_MAX_NUM_THREADS": t}
        ctx = multiprocessing.get_context("spawn")
        gpus = self.config.gpus
        counter = ctx.Value("i", 0) if gpus else None
        return ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                   initializer=_init_worker, initargs=(env, gpus, counter),
                                   max_tasks_per_child=self.config.max_tasks_per_child)

    @property
    def workers(self) -> int:
        return self.config.workers or (len(self.config.gpus) if self.config.gpus else None) or os.cpu_count() or 1

    def run(self, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
            params: np.ndarray, batch_size: int) -> Iterator[tuple[int, SimulationResult]]:
        """Yield ``(row_index, result)`` as batches complete (completion order)."""
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        todo = batches(len(params), batch_size)
        todo.reverse()
        limit = self.config.max_in_flight or 2 * self.workers
        isolate, timeout = self.config.isolate_failures, self.config.extract_timeout_s
        suspects: list[np.ndarray] = []  # batches that were in a pool when it broke, re-run alone
        pool = self._pool()
        pending: dict[Any, np.ndarray] = {}

        def failed(idx: np.ndarray, exc: BaseException, elapsed: float = 0.0) -> list[SimulationResult]:
            simulator, _ = build_plugins(simulator_spec, None)
            reason = (f"worker process died: {exc}" if isinstance(exc, BrokenProcessPool)
                      else f"{type(exc).__name__}: {exc}")
            if isinstance(exc, BrokenProcessPool) and timeout is not None and elapsed >= timeout:
                reason = (f"worker process died after {elapsed:.0f} s, past the extraction timeout ({timeout:g} s; "
                          f"an extraction stuck in native code ends its process), or it crashed: {exc}")
            return [failed_result(simulator, params[i], reason[:500]) for i in idx]

        try:
            while todo or pending or suspects:
                if suspects and not pending:
                    # a suspect runs alone, so a pool that breaks now was broken by this batch
                    idx = suspects.pop()
                    began = time.monotonic()
                    fut = pool.submit(run_batch, simulator_spec, extractor_spec, params[idx], isolate,
                                      None, timeout)
                    try:
                        results = fut.result()
                    except InvphysError:
                        raise
                    except BrokenProcessPool as exc:
                        _terminate(pool)
                        pool = self._pool()
                        if isolate and len(idx) > 1:
                            suspects.extend(np.array([i]) for i in idx[::-1])
                            continue
                        results = failed(idx, exc, time.monotonic() - began)
                    except Exception as exc:
                        results = failed(idx, exc)
                    yield from zip(idx.tolist(), results, strict=True)
                    continue
                while todo and not suspects and len(pending) < limit:
                    idx = todo.pop()
                    pending[pool.submit(run_batch, simulator_spec, extractor_spec, params[idx], isolate,
                                        None, timeout)] = idx
                done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                broken = False
                for fut in done:
                    idx = pending.pop(fut)
                    try:
                        results = fut.result()
                    except InvphysError:
                        raise
                    except BrokenProcessPool:
                        broken = True
                        suspects.append(idx)
                        continue
                    except Exception as exc:
                        results = failed(idx, exc)
                    yield from zip(idx.tolist(), results, strict=True)
                if broken:
                    suspects.extend(pending.values())
                    pending.clear()
                    _terminate(pool)
                    pool = self._pool()
        finally:
            _terminate(pool)


def _terminate(pool: Any) -> None:
    """Stop a pool now: cancel queued batches and end its worker processes."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in processes:
        if p.is_alive():
            p.terminate()
    for p in processes:
        p.join(timeout=5)
