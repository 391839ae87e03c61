"""The ``ray_actors`` executor: one long-lived warm simulator actor per GPU (or per CPU slot) of a Ray
node or cluster; idle actors pull the next chunk of rows."""

from __future__ import annotations

import json
import os
import platform
import time
from collections import deque
from collections.abc import Iterator
from typing import Any

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import Executor, PluginConfig
from invphys.core.results import SimulationResult
from invphys.plugins.executors import _batch, _deadline
from invphys.plugins.executors._extract_pool import DEFAULT_TIMEOUT_S
from invphys.plugins.executors._ray import connect, import_ray


class SimulatorActor:
    """The body of one Ray actor: a process that builds each simulator and extractor once (from their
    spec blocks, :func:`~invphys.plugins.executors._batch.build_plugins`) and keeps them, with their
    compiled kernels and allocated fields, for every chunk it runs."""

    def __init__(self, env: dict[str, str], extract_workers: int = 0,
                 extract_timeout_s: float | None = DEFAULT_TIMEOUT_S) -> None:
        os.environ.update(env)
        _deadline.DISPOSABLE = True   # an extraction stuck in native code may end this actor (Ray restarts it)
        self.extract_timeout_s = extract_timeout_s
        self.chunks = 0
        self.rows = 0
        self.busy_s = 0.0
        self.extract_workers = int(extract_workers)
        self._pools: dict[str, Any] = {}

    def _extraction_pool(self, extractor_spec: dict[str, Any] | None) -> Any:
        """The actor's warm extraction processes for ``extractor_spec`` (None without ``extract_workers``)."""
        if not self.extract_workers or not extractor_spec:
            return None
        key = json.dumps(extractor_spec, sort_keys=True, default=str)
        if key not in self._pools:
            from invphys.plugins.executors._extract_pool import ExtractionPool

            self._pools[key] = ExtractionPool(extractor_spec, self.extract_workers,
                                              timeout_s=self.extract_timeout_s)
        return self._pools[key]

    def run(self, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None, params: np.ndarray,
            isolate_failures: bool) -> list[SimulationResult]:
        """Simulate one chunk on the warm simulator (continuous batching for a ``native_stream`` one)."""
        t0 = time.perf_counter()
        try:
            return _batch.run_batch(simulator_spec, extractor_spec, params, isolate_failures,
                                    self._extraction_pool(extractor_spec), self.extract_timeout_s)
        finally:
            self.chunks += 1
            self.rows += len(np.atleast_2d(params))
            self.busy_s += time.perf_counter() - t0

    def apply(self, fn: Any, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None) -> Any:
        """``fn(simulator, extractor)`` on this actor's warm plugins (a warm-up, a counter reset)."""
        return fn(*_batch.build_plugins(simulator_spec, extractor_spec))

    def ping(self) -> bool:
        """Nothing: answers once the actor's process is up (after a restart)."""
        return True

    def info(self) -> dict[str, Any]:
        """Where this actor runs and what it has done: pid, host, Ray node id, GPU ids, chunks, rows, busy seconds,
        plugin builds (one per spec: kernels compiled once), and the slot counters of warm engines."""
        import ray

        useful = launched = 0
        for simulator, _ in _batch._CACHE.values():
            engine = getattr(simulator, "_engine", None)
            counters = getattr(engine, "counters", None)
            if counters is not None:
                useful, launched = useful + int(counters.useful), launched + int(counters.launched)
        return {"pid": os.getpid(), "host": platform.node(), "node_id": ray.get_runtime_context().get_node_id(),
                "gpu_ids": [str(g) for g in ray.get_gpu_ids()],
                "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"), "chunks": self.chunks,
                "rows": self.rows, "busy_s": self.busy_s, "builds": _batch.BUILDS,
                "extract_workers": self.extract_workers, "extraction_pools": len(self._pools),
                "useful_slot_substeps": useful, "launched_slot_substeps": launched}


class RayActorsExecutor(Executor):
    """Spreads rows over warm simulator actors of a Ray node or cluster: one actor per GPU by default.

    Each actor is a long-lived process that builds the simulator once and keeps it (compiled kernels,
    allocated fields) for every chunk, so kernels compile once per actor, not once per task. Rows are
    cut into chunks of ``chunk_size`` (default: the dataset's batch size); an actor that finishes a chunk
    pulls the next one, so a slow GPU does not hold the others up, and results stream back chunk by chunk.
    A simulator with continuous batching (``native_stream``) streams each chunk through its slots: make
    chunks a few times its ``batch_size`` so slots stay full. With ``num_gpus: 0`` the actors are CPU
    processes.

    Failures are per row: a chunk whose simulator raises is re-run row by row inside the actor
    (``isolate_failures``); an actor that dies (segfault, out of memory) is restarted by Ray (at most
    ``max_restarts`` times) and the rows of its chunk are re-run one at a time, each alone on an actor,
    so only the rows that kill an actor are stored as failed (``ray actor died: ...``). An actor that
    died gets no rows until it answers a ping: a ping that finds it still restarting
    (``ActorUnavailableError``) is tried again after a short back-off, at most ``unavailable_retries``
    times, so a row is never failed for reaching an actor that Ray had not brought back yet.

    With ``keep_actors`` the actors (and a Ray instance this executor started) live on after ``run`` for
    the next call on the same executor (simulator-in-the-loop optimisation, active learning); a later
    run with a smaller ``config.actors`` uses the first actors of the warm pool. :meth:`warm` and
    :meth:`apply` prepare the actors' plugins, :meth:`actor_info` reports on them, :meth:`close`
    releases them.
    """

    name = "ray_actors"

    class Config(PluginConfig):
        address: str | None = Field(None, description="Ray cluster address; None starts a local instance")
        num_cpus: int | None = Field(None, ge=1, description="CPUs of a local instance (default: all)")
        num_gpus: float = Field(
            1.0, ge=0, description="GPUs each actor holds (1: one actor per GPU; 0: CPU actors)")
        num_cpus_per_actor: float = Field(
            1.0, ge=0, description="CPUs each actor holds; also its OMP/MKL/taichi CPU threads (at least 1)")
        actors: int | None = Field(
            None, ge=1, description="number of actors (default: cluster GPUs / num_gpus, or CPUs / "
                                    "num_cpus_per_actor for CPU actors)")
        chunk_size: int | None = Field(
            None, ge=1, description="rows an actor pulls at a time (default: the dataset's batch size)")
        prefetch: int = Field(
            0, ge=0, description="chunks queued on a busy actor beyond the one it runs (0: pull when idle)")
        max_restarts: int = Field(8, ge=0, description="restarts of an actor whose process died")
        unavailable_retries: int = Field(
            20, ge=0, description="pings of a restarting actor before it counts as dead (back-off <= 2 s)")
        isolate_failures: bool = Field(
            True, description="when a chunk raises, re-run its rows one by one so only the bad row fails")
        extract_workers: int = Field(
            0, ge=0, le=64, description="processes per actor extracting features while its simulator goes on "
                                        "(0: in the actor, between launches); CPUs beyond num_cpus_per_actor")
        extract_timeout_s: float | None = Field(
            DEFAULT_TIMEOUT_S, gt=0, description="seconds one run's feature extraction may take (in the actor "
                                                 "or its extraction processes) before it is stopped and the "
                                                 "run recorded as failed (null: no limit)")
        runtime_env: dict[str, Any] | None = Field(None, description="Ray runtime_env of the actors")
        keep_actors: bool = Field(
            False, description="keep the warm actors (and a Ray instance started here) after run for the "
                               "next call; close() releases them")

    def __init__(self, config: PluginConfig | dict[str, Any] | None = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._ray: Any = None
        self._started = False
        self._actors: list[Any] = []

    # -- the actor pool ----------------------------------------------------------------------
    def _connect(self) -> Any:
        if self._ray is None or not self._ray.is_initialized():
            self._ray = ray = import_ray(self.name)
            self._started = connect(ray, self.config.address, self.config.num_cpus) or self._started
            self._actors = []
        return self._ray

    def _size(self, ray: Any) -> int:
        """Actors to start, checked against the cluster's GPUs and CPUs."""
        cfg = self.config
        resources = ray.cluster_resources()
        gpus, cpus = float(resources.get("GPU", 0)), float(resources.get("CPU", 0))
        where = f"Ray at {cfg.address!r}" if cfg.address else "the local Ray instance"
        if cfg.num_gpus > 0:
            if gpus < cfg.num_gpus:
                raise InvphysError(
                    f"executor 'ray_actors' asks for {cfg.num_gpus:g} GPU per actor but {where} sees "
                    f"{gpus:g} GPUs (set num_gpus: 0 for CPU actors)")
            n = cfg.actors or int(gpus // cfg.num_gpus + 1e-9)
            if n * cfg.num_gpus > gpus + 1e-9:
                raise InvphysError(f"executor 'ray_actors': {n} actors x {cfg.num_gpus:g} GPUs need "
                                   f"{n * cfg.num_gpus:g} GPUs but {where} has {gpus:g}")
        else:
            n = cfg.actors or max(1, int(cpus // cfg.num_cpus_per_actor + 1e-9) if cfg.num_cpus_per_actor else 1)
        if n * cfg.num_cpus_per_actor > cpus + 1e-9:
            raise InvphysError(f"executor 'ray_actors': {n} actors x {cfg.num_cpus_per_actor:g} CPUs need "
                               f"{n * cfg.num_cpus_per_actor:g} CPUs but {where} has {cpus:g}")
        return n

    def _pool(self) -> list[Any]:
        """The warm actors, started on first use."""
        ray = self._connect()
        if not self._actors:
            cfg = self.config
            threads = str(max(1, int(cfg.num_cpus_per_actor)))
            env = {"OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, "OPENBLAS_NUM_THREADS": threads,
                   "TI_CPU_MAX_NUM_THREADS": threads}
            options: dict[str, Any] = {"num_cpus": cfg.num_cpus_per_actor, "num_gpus": cfg.num_gpus,
                                       "max_restarts": cfg.max_restarts, "max_task_retries": 0}
            if cfg.runtime_env:
                options["runtime_env"] = cfg.runtime_env
            actor_cls = ray.remote(SimulatorActor).options(**options)
            self._actors = [actor_cls.remote(env, cfg.extract_workers, cfg.extract_timeout_s)
                            for _ in range(self._size(ray))]
        return self._actors

    def warm(self, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
             params: np.ndarray) -> None:
        """Run ``params`` once on every actor (results dropped): builds the plugins and compiles their
        kernels everywhere before timed or latency-bound work."""
        pool = self._pool()
        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        self._ray.get([a.run.remote(simulator_spec, extractor_spec, params, True) for a in pool])

    def apply(self, fn: Any, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None) -> list[Any]:
        """``fn(simulator, extractor)`` on every actor's warm plugins (built there once per spec), in
        parallel; their return values. ``fn`` must be importable on the actors (a module-level function)."""
        pool = self._pool()
        return self._ray.get([a.apply.remote(fn, simulator_spec, extractor_spec) for a in pool])

    def actor_info(self) -> list[dict[str, Any]]:
        """:meth:`SimulatorActor.info` of every actor of the pool (empty before the first run)."""
        return self._ray.get([a.info.remote() for a in self._actors]) if self._actors else []

    def close(self) -> None:
        """Kill the actors and shut down a Ray instance this executor started."""
        ray, actors, self._actors = self._ray, self._actors, []
        if ray is None:
            return
        for actor in actors:
            try:
                ray.kill(actor)
            except Exception:
                pass
        if self._started and ray.is_initialized():
            ray.shutdown()
        self._started = False

    # -- running -------------------------------------------------------------------------------
    def run(self, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
            params: np.ndarray, batch_size: int) -> Iterator[tuple[int, SimulationResult]]:
        """Yield ``(row_index, result)`` as chunks finish (completion order)."""
        try:
            pool = self._pool()
            yield from self._run(pool, simulator_spec, extractor_spec, params, batch_size)
        finally:
            if not self.config.keep_actors:
                self.close()

    def _run(self, pool: list[Any], simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
             params: np.ndarray, batch_size: int) -> Iterator[tuple[int, SimulationResult]]:
        ray, cfg = self._ray, self.config
        pool = pool[:min(len(pool), cfg.actors or len(pool))]   # a smaller `actors` later: the first ones
        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        plan = _Schedule(ray, cfg, pool, deque(_batch.batches(len(params), cfg.chunk_size or batch_size)),
                         lambda actor, idx: actor.run.remote(simulator_spec, extractor_spec, params[idx],
                                                             cfg.isolate_failures))

        def failed(idx: np.ndarray, reason: str) -> list[SimulationResult]:
            simulator, _ = _batch.build_plugins(simulator_spec, None)
            return [_batch.failed_result(simulator, params[i], reason[:500]) for i in idx]

        try:
            while plan.todo or plan.suspects or plan.inflight:
                plan.assign()
                waits = plan.waits()
                if not plan.inflight and waits:   # only actors still restarting: ping the first again
                    time.sleep(max(min(waits), 0.0))
                    continue
                if not plan.inflight:   # every actor died too often: the rest cannot run
                    reason = (f"ray actor died more than max_restarts={cfg.max_restarts} times "
                              f"(or did not come back after {cfg.unavailable_retries} pings)")
                    for idx in [*plan.suspects, *plan.todo]:
                        yield from zip(idx.tolist(), failed(idx, reason), strict=True)
                    return
                done, _ = ray.wait(list(plan.inflight), num_returns=1,
                                   timeout=max(min(waits), 0.0) if waits else None)
                for ref in done:
                    got = plan.collect(ref)
                    if got is not None:
                        idx, results = got
                        if isinstance(results, str):
                            results = failed(idx, results)
                        yield from zip(idx.tolist(), results, strict=True)
        finally:
            plan.cancel()


class _Schedule:
    """Which actor runs which chunk in one :meth:`RayActorsExecutor.run` (see its class text): idle actors
    pull chunks (``todo``); the rows of a chunk whose actor died are re-run one at a time, each alone on an
    actor (``suspects``); an actor that died gets no rows until it answers a ping."""

    def __init__(self, ray: Any, cfg: Any, pool: list[Any], todo: deque[np.ndarray],
                 call: Any) -> None:
        from ray.exceptions import RayActorError

        try:
            from ray.exceptions import ActorUnavailableError
        except ImportError:   # a Ray without that state (before 2.10)
            ActorUnavailableError = RayActorError  # type: ignore[misc,assignment]
        self._died, self._unavailable = RayActorError, ActorUnavailableError
        self.ray, self.cfg, self.pool, self.todo, self.call = ray, cfg, pool, todo, call
        self.suspects: deque[np.ndarray] = deque()   # rows of a chunk whose actor died: each re-run alone
        self.load = [0] * len(pool)                   # chunks in flight per actor
        self.deaths = [0] * len(pool)
        self.alone: set[int] = set()                  # actors running a suspect row or a ping (nothing else)
        self.unpinged: dict[int, tuple[float, int]] = {}   # actor that died -> (ping no earlier than, pings)
        #: ref -> (actor, rows, alone) or (actor, None, pings)
        self.inflight: dict[Any, tuple[int, np.ndarray | None, int]] = {}

    def live(self) -> list[int]:
        return [a for a in range(len(self.pool)) if self.deaths[a] <= self.cfg.max_restarts]

    def submit(self, a: int, idx: np.ndarray, single: bool) -> None:
        self.inflight[self.call(self.pool[a], idx)] = (a, idx, single)
        self.load[a] += 1
        if single:
            self.alone.add(a)

    def ping(self, a: int) -> None:
        _, tries = self.unpinged.pop(a)
        self.inflight[self.pool[a].ping.remote()] = (a, None, tries)
        self.load[a] += 1
        self.alone.add(a)

    def ping_failed(self, a: int, tries: int, exc: Exception) -> None:
        if isinstance(exc, self._unavailable) and tries < self.cfg.unavailable_retries:
            self.unpinged[a] = (time.monotonic() + min(0.05 * 2 ** (tries + 1), 2.0), tries + 1)
        else:   # gone for good, or restarting for too long
            self.deaths[a] = self.cfg.max_restarts + 1

    def assign(self) -> None:
        """Give idle live actors work: a due ping, a suspect row (alone), or the next chunk."""
        now = time.monotonic()
        for a in sorted(self.live(), key=lambda k: self.load[k]):   # idle actors pull first
            if a in self.unpinged and self.load[a] == 0 and self.unpinged[a][0] <= now:
                self.ping(a)
            if a in self.alone or a in self.unpinged:
                continue
            if self.suspects and self.load[a] == 0:
                self.submit(a, self.suspects.popleft(), True)
            elif self.todo and not self.suspects and self.load[a] <= self.cfg.prefetch:
                self.submit(a, self.todo.popleft(), False)

    def waits(self) -> list[float]:
        """Seconds until each live actor that is restarting may be pinged."""
        now = time.monotonic()
        return [self.unpinged[a][0] - now for a in self.live() if a in self.unpinged]

    def collect(self, ref: Any) -> tuple[np.ndarray, list[SimulationResult] | str] | None:
        """A finished call's rows with their results, or with the reason they failed; None for a ping or
        for rows queued again as suspects. An :class:`InvphysError` raised in the actor propagates."""
        a, idx, single = self.inflight.pop(ref)
        self.load[a] -= 1
        self.alone.discard(a)
        try:
            results = self.ray.get(ref)
        except Exception as exc:
            if idx is None:
                self.ping_failed(a, single, exc)
                return None
            cause = getattr(exc, "cause", None) or exc
            if isinstance(cause, InvphysError):
                raise InvphysError(str(cause)) from exc
            died = isinstance(exc, self._died)
            self.deaths[a] += died
            if died and self.deaths[a] <= self.cfg.max_restarts:
                self.unpinged.setdefault(a, (0.0, 0))   # no rows until it answers a ping
            if died and not single and (self.cfg.isolate_failures or len(idx) == 1):
                self.suspects.extend(np.array([i]) for i in idx)   # find the row that kills it
                return None
            kind = "ray actor died" if died else "ray actor call failed"
            return idx, f"{kind}: {type(cause).__name__}: {cause}"
        return (idx, results) if idx is not None else None

    def cancel(self) -> None:
        for ref in self.inflight:
            try:
                self.ray.cancel(ref)
            except Exception:
                pass
