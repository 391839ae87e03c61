"""Running one batch of simulations where an executor puts it (this process, a pool worker, a Ray task).

Plugins are rebuilt from their ``{"type": name, **config}`` blocks and cached per process, so a worker
initialises a simulator backend (taichi, warp) once and reuses it for every batch it runs.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.results import RunStats, SimulationResult
from invphys.core.stream import stream_until_broken, unreturned
from invphys.plugins.executors import _deadline
from invphys.plugins.executors._extract_pool import DEFAULT_TIMEOUT_S

_CACHE: dict[str, tuple[Any, Any]] = {}
#: plugin builds in this process (a warm worker builds once per spec, whatever the number of batches)
BUILDS = 0


def build_plugins(simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None) -> tuple[Any, Any]:
    """The (simulator, extractor) for these blocks, built once per process through the registry."""
    global BUILDS
    key = json.dumps([simulator_spec, extractor_spec], sort_keys=True, default=str)
    if key not in _CACHE:
        BUILDS += 1
        from invphys import registry

        simulator = registry.create("simulator", dict(simulator_spec))
        extractor = registry.create("feature_extractor", dict(extractor_spec)) if extractor_spec else None
        _CACHE[key] = (simulator, extractor)
    return _CACHE[key]


def failed_result(simulator: Any, params: np.ndarray, reason: str, wall_time_s: float = 0.0) -> SimulationResult:
    """A failed :class:`SimulationResult` for a run that raised instead of returning."""
    cfg = getattr(simulator, "config", None)
    stats = RunStats(wall_time_s=wall_time_s, backend=str(getattr(cfg, "backend", "") or ""),
                     preset=str(getattr(cfg, "preset", "") or ""), simulator=str(simulator.name),
                     simulator_version=str(simulator.version))
    return SimulationResult(params=np.asarray(params, dtype=np.float64), ok=False, stats=stats, failure=reason)


def _reason(exc: BaseException) -> str:
    from invphys.core.dataset import failure_reason

    return failure_reason(exc)


def _finish(res: SimulationResult, extractor: Any, timeout_s: float | None = DEFAULT_TIMEOUT_S) -> None:
    """Extract the features of an ok result (within ``timeout_s``: :mod:`._deadline`) and drop its
    trajectory (idempotent)."""
    if extractor is None:
        return
    if res.ok and res.features is None:
        try:
            if res.trajectory is None:
                raise RuntimeError("the simulator returned no trajectory")
            res.features = np.asarray(_deadline.call(extractor.extract, timeout_s, res.trajectory),
                                      dtype=np.float64)
        except InvphysError:
            raise
        except Exception as exc:
            res.ok, res.failure = False, f"feature extraction: {_reason(exc)}"
    res.trajectory = None


def simulate_batch(simulator: Any, extractor: Any, params: np.ndarray, isolate_failures: bool = True,
                   pool: Any = None, timeout_s: float | None = DEFAULT_TIMEOUT_S) -> list[SimulationResult]:
    """Simulate ``params`` (B, d) in one simulator call and extract features.

    Features are extracted as the simulator reports each run (``on_result``), so trajectories are
    dropped as soon as possible and a large call holds few of them at once; with an
    :class:`~invphys.plugins.executors._extract_pool.ExtractionPool` the run is handed to a worker
    process instead and the simulator goes on at once. An exception from the simulator (other than an
    :class:`InvphysError`, which is the user's to fix and propagates) becomes failed results: with
    ``isolate_failures`` the rows of a multi-row batch are re-run one by one so that one bad row does
    not fail its neighbours. An extraction in this process that runs past ``timeout_s`` is its run's
    failure (:mod:`._deadline`). Results carry ``features``, never a trajectory.
    """
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    pending: dict[int, Any] = {}

    def on_result(i: int, res: SimulationResult) -> None:
        if pool is None or extractor is None:
            _finish(res, extractor, timeout_s)
        elif int(i) not in pending:
            pending[int(i)] = pool.submit(res)

    t0 = time.perf_counter()
    try:
        results = list(simulator.simulate(params, on_result=on_result))
        if len(results) != len(params):
            raise RuntimeError(f"simulator returned {len(results)} results for {len(params)} rows")
    except InvphysError:
        raise
    except Exception as exc:
        for fut in pending.values():  # runs already handed over are re-run with the rest
            if fut is not None:
                fut.cancel()
        pending.clear()
        if isolate_failures and len(params) > 1:
            results = [simulate_batch(simulator, extractor, row[None], False, pool, timeout_s)[0] for row in params]
        else:
            wall = (time.perf_counter() - t0) / len(params)
            results = [failed_result(simulator, row, _reason(exc), wall) for row in params]
    if pool is not None and extractor is not None:
        for i, res in enumerate(results):  # runs the simulator did not report one by one
            if i not in pending:
                pending[i] = pool.submit(res)
        for i, res in enumerate(results):
            pool.resolve(res, pending.get(i))
    for res in results:
        _finish(res, extractor, timeout_s)
        res.trajectory = None
    return results


def stream_rows(simulator: Any, extractor: Any, params: np.ndarray, batch_size: int | None = None,
                isolate_failures: bool = True, pool: Any = None, timeout_s: float | None = DEFAULT_TIMEOUT_S
                ) -> Iterator[tuple[int, SimulationResult]]:
    """Yield ``(row, result)`` through :meth:`Simulator.simulate_stream` (continuous batching on a warm
    simulator), features extracted and trajectories dropped as runs finish (with a ``pool``: in worker
    processes, each row yielded once its features are back, so rows may come out of finishing order).
    If the stream raises (other than an :class:`InvphysError`), the rows it has not returned go through
    :func:`simulate_batch` instead, so one bad row fails alone as on the batch path
    (:func:`~invphys.core.stream.stream_until_broken`)."""
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    seen: set[int] = set()
    pending: dict[int, tuple[SimulationResult, Any]] = {}

    def ready(wait: bool) -> Iterator[tuple[int, SimulationResult]]:
        for j in [j for j, (_, fut) in pending.items() if wait or fut is None or fut.done()]:
            res, fut = pending.pop(j)
            yield j, pool.resolve(res, fut)

    for i, res in stream_until_broken(simulator, params, batch_size, seen):
        if pool is None or extractor is None:
            _finish(res, extractor, timeout_s)
            yield i, res
        else:
            pending[i] = (res, pool.submit(res))
            yield from ready(False)
    yield from ready(True)
    rest = np.array(unreturned(len(params), seen), dtype=np.int64)
    if len(rest):
        yield from zip(rest.tolist(), simulate_batch(simulator, extractor, params[rest], isolate_failures, pool,
                                                     timeout_s), strict=True)


def run_batch(simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None, params: np.ndarray,
              isolate_failures: bool = True, pool: Any = None,
              timeout_s: float | None = DEFAULT_TIMEOUT_S) -> list[SimulationResult]:
    """Build (or reuse) the plugins and simulate one batch: the function workers execute (features
    extracted in ``pool``'s processes while the simulator goes on, where one is given; else here, within
    ``timeout_s`` per run)."""
    simulator, extractor = build_plugins(simulator_spec, extractor_spec)
    if getattr(simulator, "native_stream", False):   # continuous batching inside the task
        out: list[SimulationResult | None] = [None] * len(np.atleast_2d(params))
        for i, res in stream_rows(simulator, extractor, params, None, isolate_failures, pool, timeout_s):
            out[i] = res
        return [r for r in out if r is not None]
    return simulate_batch(simulator, extractor, params, isolate_failures, pool, timeout_s)


def batches(n: int, batch_size: int) -> list[np.ndarray]:
    """Row indices ``0..n-1`` cut into consecutive batches of at most ``batch_size``."""
    if batch_size <= 0:
        raise InvphysError(f"batch_size must be > 0, got {batch_size}")
    return [np.arange(i, min(i + batch_size, n)) for i in range(0, n, batch_size)]
