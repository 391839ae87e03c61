"""The ``ray`` executor: batches as Ray tasks on a local or remote Ray cluster."""

from __future__ import annotations

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
from invphys.plugins.executors._ray import connect, import_ray


def _task(simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None, params: np.ndarray,
          isolate_failures: bool, timeout_s: float | None) -> list[SimulationResult]:
    """One batch in a Ray worker (a process that only runs tasks: a stuck extraction may end it)."""
    _deadline.DISPOSABLE = True
    return run_batch(simulator_spec, extractor_spec, params, isolate_failures, None, timeout_s)


class RayExecutor(Executor):
    """Runs each batch as a Ray task, for users who outgrow one machine.

    Connects to ``address`` (e.g. ``"auto"`` or ``"ray://head:10001"``) or starts a local Ray instance.
    Tasks ask for ``num_gpus`` GPUs each (fractions share a GPU), are retried ``max_retries`` times
    when their worker dies, and at most ``max_in_flight`` are submitted at once. A batch whose task
    still fails is re-run row by row (with ``isolate_failures``), and the rows that fail alone are
    stored as failed with the error text. A run whose feature extraction takes longer than
    ``extract_timeout_s`` is interrupted and recorded as failed (:mod:`._deadline`). Workers rebuild the
    plugins from their spec blocks, so plugins must be importable on every node.
    """

    name = "ray"

    class Config(PluginConfig):
        address: str | None = Field(None, description="Ray cluster address; None starts a local instance")
        num_cpus: int | None = Field(None, ge=1, description="CPUs of a local instance (default: all)")
        num_cpus_per_task: float = Field(1.0, ge=0, description="CPUs each batch task reserves")
        num_gpus: float = Field(0.0, ge=0, description="GPUs each batch task reserves (0.25 = 4 per GPU)")
        max_retries: int = Field(2, ge=0, description="re-runs of a task whose worker process died")
        max_in_flight: int | None = Field(
            None, ge=1, description="tasks submitted but not finished (default: 2 x cluster CPUs / task CPUs)")
        isolate_failures: bool = Field(
            True, description="when a batch raises, re-run its rows one by one so only the bad row fails")
        runtime_env: dict[str, Any] | None = Field(None, description="Ray runtime_env for the tasks")
        extract_timeout_s: float | None = Field(
            DEFAULT_TIMEOUT_S, gt=0, description="seconds one run's feature extraction may take in a task "
                                                 "before it is interrupted and the run recorded as failed "
                                                 "(null: no limit)")
        shutdown: bool = Field(True, description="shut down a local instance this executor started")

    def run(self, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
            params: np.ndarray, batch_size: int) -> Iterator[tuple[int, SimulationResult]]:
        """Yield ``(row_index, result)`` as tasks complete (completion order)."""
        cfg = self.config
        ray = import_ray(self.name)
        started = connect(ray, cfg.address, cfg.num_cpus)
        try:
            yield from self._run(ray, simulator_spec, extractor_spec, params, batch_size)
        finally:
            if started and cfg.shutdown:
                ray.shutdown()

    def _run(self, ray: Any, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
             params: np.ndarray, batch_size: int) -> Iterator[tuple[int, SimulationResult]]:
        cfg = self.config
        options: dict[str, Any] = {"num_cpus": cfg.num_cpus_per_task, "num_gpus": cfg.num_gpus,
                                   "max_retries": cfg.max_retries}
        if cfg.runtime_env:
            options["runtime_env"] = cfg.runtime_env
        task = ray.remote(_task).options(**options)
        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        todo = batches(len(params), batch_size)
        todo.reverse()
        limit = cfg.max_in_flight or max(
            1, int(2 * ray.cluster_resources().get("CPU", 1) / max(cfg.num_cpus_per_task, 1e-9)))
        pending: dict[Any, np.ndarray] = {}
        try:
            while todo or pending:
                while todo and len(pending) < limit:
                    idx = todo.pop()
                    pending[task.remote(simulator_spec, extractor_spec, params[idx], cfg.isolate_failures,
                                        cfg.extract_timeout_s)] = idx
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    idx = pending.pop(ref)
                    try:
                        results = ray.get(ref)
                    except Exception as exc:
                        cause = getattr(exc, "cause", None) or exc
                        if isinstance(cause, InvphysError):
                            raise InvphysError(str(cause)) from exc
                        if cfg.isolate_failures and len(idx) > 1:
                            todo.extend(np.array([i]) for i in idx[::-1])  # find the row that fails
                            continue
                        simulator, _ = build_plugins(simulator_spec, None)
                        reason = f"ray task failed: {type(cause).__name__}: {cause}"[:500]
                        results = [failed_result(simulator, params[i], reason) for i in idx]
                    yield from zip(idx.tolist(), results, strict=True)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)
