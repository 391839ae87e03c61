"""The ``local`` executor: batches run one after another in this process."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from pydantic import Field

from invphys.core.interfaces import Executor, PluginConfig
from invphys.core.results import SimulationResult
from invphys.plugins.executors._batch import batches, build_plugins, simulate_batch, stream_rows
from invphys.plugins.executors._extract_pool import DEFAULT_TIMEOUT_S


class LocalExecutor(Executor):
    """Runs each batch in this process through the simulator's own batching (a GPU simulator advances
    the whole batch at once on its device). The default executor."""

    name = "local"

    class Config(PluginConfig):
        isolate_failures: bool = Field(
            True, description="when a batch raises, re-run its rows one by one so only the bad row fails")
        extract_workers: int = Field(
            0, ge=0, le=256, description="extract features in this many worker processes while the simulator "
                                         "goes on (0: in this process, between launches)")
        extract_timeout_s: float | None = Field(
            DEFAULT_TIMEOUT_S, gt=0, description="seconds one run's feature extraction may take before it is "
                                                 "stopped and the run recorded as failed (in a worker process: "
                                                 "the process is stopped; in this process: the extractor's "
                                                 "Python code is interrupted; null: no limit)")

    def run(self, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
            params: np.ndarray, batch_size: int) -> Iterator[tuple[int, SimulationResult]]:
        """Yield ``(row_index, result)`` batch by batch, in row order; for a simulator with
        ``native_stream`` (continuous batching), every row in one stream, in completion order."""
        simulator, extractor = build_plugins(simulator_spec, extractor_spec)
        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        pool = None
        if self.config.extract_workers and extractor_spec:
            from invphys.plugins.executors._extract_pool import ExtractionPool

            pool = ExtractionPool(extractor_spec, self.config.extract_workers,
                                  timeout_s=self.config.extract_timeout_s)
        try:
            if getattr(simulator, "native_stream", False):
                # one stream over every row: the simulator keeps its slots full across batch boundaries
                yield from stream_rows(simulator, extractor, params, None, self.config.isolate_failures, pool,
                                       self.config.extract_timeout_s)
                return
            for idx in batches(len(params), batch_size):
                results = simulate_batch(simulator, extractor, params[idx], self.config.isolate_failures, pool,
                                         self.config.extract_timeout_s)
                yield from zip(idx.tolist(), results, strict=True)
        finally:
            if pool is not None:
                pool.close()
