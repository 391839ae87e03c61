"""Feature extraction in worker processes, off the thread that drives the simulator.

A GPU simulator hands each finished run to the host between launches; extracting its features there
(~0.14 s per paper-preset orange-peel run on one core of the H100 host) leaves the GPU idle meanwhile,
and threads do not help (the extractor's KD-trees hold the GIL). :class:`ExtractionPool` sends each
trajectory to one of ``workers`` processes (started with ``spawn``, so a CUDA context or a Taichi
runtime of the parent is never forked) and returns at once; the caller collects the features later.
Each worker builds the extractor once: from its ``{"type": ..., **config}`` block through the registry,
or unpickles the extractor instance it was given.
"""

from __future__ import annotations

from concurrent.futures import Future, ProcessPoolExecutor
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.results import SimulationResult

_WORKER_EXTRACTOR: Any = None


def _init_worker(extractor: Any) -> None:
    global _WORKER_EXTRACTOR
    if isinstance(extractor, dict):
        from invphys import registry

        extractor = registry.create("feature_extractor", dict(extractor))
    _WORKER_EXTRACTOR = extractor


def _extract(trajectory: Any) -> np.ndarray:
    return np.asarray(_WORKER_EXTRACTOR.extract(trajectory), dtype=np.float64)


class ExtractionPool:
    """``workers`` processes extracting features with ``extractor`` (a plugin block or an instance)."""

    def __init__(self, extractor: Any, workers: int) -> None:
        import multiprocessing

        if workers < 1:
            raise InvphysError(f"extract_workers must be >= 1 for a pool, got {workers}")
        self.workers = int(workers)
        self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_worker,
                                         initargs=(dict(extractor) if isinstance(extractor, dict) else extractor,))

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
        """Extract one trajectory's features in a worker (the future raises what the extractor raised)."""
        return self._pool.submit(_extract, trajectory)

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
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ExtractionPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
