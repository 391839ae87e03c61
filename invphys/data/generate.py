"""Dataset generation: sample parameters, simulate them through an executor, store every row.

:func:`generate_dataset` is what ``invphys dataset generate`` and the ``dataset`` stage run::

    from invphys.data.generate import generate_dataset
    summary = generate_dataset("data/peel", simulator={"type": "orange_peel", "preset": "tiny"},
                               n=64, batch_size=8, executor={"type": "process", "workers": 2})
    print(summary.ok, summary.failed, summary.runs_per_hour)

The design is deterministic in ``(n, sampler, seed)``; rows already in the store (same key) are skipped,
so re-running the same call resumes a killed or time-limited generation and never duplicates.
"""

from __future__ import annotations

import contextlib
import os
import platform
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.dataset import DatasetStore, Row, RunIdentity, check_features, round_theta, row_keys
from invphys.core.errors import InvphysError
from invphys.core.sampling import sample_unit


@dataclass
class GenerationSummary:
    """What one generation session did (JSON-ready through :meth:`to_dict`)."""

    path: str
    requested: int
    already_present: int
    #: stored rows that are not points of this design (another n, seed or sampler made them)
    other_rows: int = 0
    ran: int = 0
    ok: int = 0
    failed: int = 0
    wall_s: float = 0.0
    stop_reason: str = "running"
    total_rows: int = 0
    total_ok: int = 0
    total_failed: int = 0
    devices: list[str] = field(default_factory=list)
    backends: list[str] = field(default_factory=list)
    #: an adaptive design's settings and its rounds' records (None for a sampler's design)
    design: dict[str, Any] | None = None

    @property
    def runs_per_hour(self) -> float:
        return 3600.0 * self.ran / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def complete(self) -> bool:
        """True when every requested row is in the store."""
        return self.already_present + self.ran >= self.requested

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "runs_per_hour": round(self.runs_per_hour, 1), "complete": self.complete}


class _Terminated(BaseException):  # like KeyboardInterrupt: never caught as a simulation error
    """SIGTERM arrived: stop cleanly, keeping what is stored."""


class _Stopper:
    """SIGTERM and Ctrl-C stop a generation, but never in the middle of storing rows.

    Outside :meth:`critical` a signal raises at once (interrupting a simulation); inside, it is held
    and raised when the critical section ends, so a row is either stored and counted or neither.
    After :meth:`stopping` further signals are ignored while the last rows are flushed.
    """

    def __init__(self) -> None:
        self.depth = 0
        self.pending: BaseException | None = None
        self.done = False

    def handler(self, signum: int, frame: Any) -> None:
        if self.done:
            return
        exc: BaseException = KeyboardInterrupt() if signum == signal.SIGINT else _Terminated()
        if self.depth:
            self.pending = self.pending or exc
            return
        raise exc

    @contextlib.contextmanager
    def critical(self) -> Iterator[None]:
        self.depth += 1
        try:
            yield
        finally:
            self.depth -= 1
        if not self.depth and self.pending is not None and not self.done:
            exc, self.pending = self.pending, None
            raise exc

    def stopping(self) -> None:
        self.done, self.pending = True, None

    @contextlib.contextmanager
    def installed(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {sig: signal.signal(sig, self.handler) for sig in (signal.SIGTERM, signal.SIGINT)}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


def _utcnow() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def host_info() -> dict[str, Any]:
    """Where a generation ran (recorded in the dataset's metadata)."""
    return {"hostname": platform.node(), "platform": platform.platform(), "python": sys.version.split()[0],
            "cpu_count": os.cpu_count()}


#: generation orders rows costliest first within consecutive windows of this many batches (design order)
COST_WINDOW_BATCHES = 4


def _costliest_first(sim: Any, params: np.ndarray, todo: np.ndarray, window: int | None = None) -> np.ndarray:
    """``todo`` (row indices) ordered costliest first by the simulator's :meth:`estimate_cost` within
    consecutive windows of ``window`` rows in design order (None: one window), so that a batch holds runs of
    similar cost and the longest of a window start early (several workers end together), while a session
    stopped early (``--limit-minutes``) has stored about the design's first rows, not its costliest ones
    (those would be a biased sample of the design); the design order where the simulator has no estimate.
    Stored rows do not depend on the order."""
    if len(todo) < 2:
        return todo
    try:
        cost = sim.estimate_cost(params[todo])
    except InvphysError:   # a row out of range: it fails on its own when simulated
        return todo
    if cost is None:
        return todo
    cost = np.asarray(cost, dtype=np.float64).reshape(-1)
    name = type(sim).__name__
    if cost.shape != todo.shape:
        raise InvphysError(f"{name}.estimate_cost gave {len(cost)} values for {len(todo)} rows")
    if not np.isfinite(cost).all():
        raise InvphysError(f"{name}.estimate_cost gave a non-finite cost")
    step = len(todo) if window is None else max(1, int(window))
    return np.concatenate([todo[start:start + step][np.argsort(-cost[start:start + step], kind="stable")]
                           for start in range(0, len(todo), step)])


def generate_dataset(
    path: str | os.PathLike[str],
    simulator: dict[str, Any],
    features: dict[str, Any] | None = None,
    executor: dict[str, Any] | None = None,
    n: int = 200,
    sampler: str = "uniform",
    batch_size: int = 16,
    seed: int = 0,
    limit_minutes: float | None = None,
    spec: dict[str, Any] | None = None,
    progress: bool = True,
    console: Any = None,
    registry: Any = None,
    flush_every_s: float = 30.0,
    adaptive: Any = None,
    points: np.ndarray | None = None,
    index_offset: int = 0,
    design: dict[str, Any] | None = None,
) -> GenerationSummary:
    """Generate (or resume) the dataset of ``n`` runs in the store at ``path``.

    ``simulator``/``features``/``executor`` are plugin blocks ``{"type": name, **config}``; ``features``
    None uses the simulator's default extractor and ``executor`` None the ``local`` executor. Rows are
    stored after every batch (and at least every ``flush_every_s`` seconds). With ``limit_minutes`` the
    run stops before starting a batch it expects to finish after the limit (summary ``stop_reason``
    ``"time_limit"``); SIGTERM and Ctrl-C also stop cleanly. ``spec`` (the experiment spec as a dict)
    is recorded in the metadata.

    ``adaptive`` (a ``dataset.adaptive`` block) generates the first ``adaptive.initial`` runs by the
    sampler and the rest in rounds where a surrogate is least sure (:mod:`invphys.data.adaptive`).
    ``points`` (unit-cube rows) replaces the sampler's design by these points, stored with sample
    indices from ``index_offset``; ``design`` is recorded in the session (both are what the adaptive
    rounds use).
    """
    from invphys import registry as registry_module

    if adaptive is not None:
        from invphys.data.adaptive import generate_adaptive

        return generate_adaptive(path, n=n, sampler=sampler, seed=seed, adaptive=adaptive,
                                 limit_minutes=limit_minutes, progress=progress, console=console,
                                 registry=registry, simulator=simulator, features=features, executor=executor,
                                 batch_size=batch_size, spec=spec, flush_every_s=flush_every_s,
                                 generate=generate_dataset)

    plan = _plan(registry or registry_module.default_registry(), simulator, features, executor,
                 n=n, sampler=sampler, seed=seed, batch_size=batch_size, points=points)
    store = DatasetStore(path)
    with store.writer():
        run, todo = _open_session(store, plan, sampler=sampler, seed=seed, batch_size=batch_size,
                                  limit_minutes=limit_minutes, spec=spec, design=design, progress=progress,
                                  console=console)
        run.flush([])
        if len(todo):
            _simulate(plan, run, todo, batch_size=batch_size, limit_minutes=limit_minutes,
                      flush_every_s=flush_every_s, index_offset=index_offset, progress=progress, console=console)
        summary = run.summary
        if summary.stop_reason == "running":
            summary.stop_reason = "complete" if summary.complete else "incomplete"
        run.flush([])
    return summary


@dataclass
class _Plan:
    """What one generation runs: the plugins and their blocks, the design (``theta`` normalised, ``params``
    physical) and each design point's row key."""

    sim: Any
    sim_block: dict[str, Any]
    ext_block: dict[str, Any]
    exec_block: dict[str, Any]
    executor: Any
    extractor: Any
    space: Any
    identity: RunIdentity
    theta: np.ndarray
    params: np.ndarray
    keys: list[str]

    @property
    def n(self) -> int:
        return len(self.keys)


def _plan(reg: Any, simulator: dict[str, Any], features: dict[str, Any] | None, executor: dict[str, Any] | None,
          n: int, sampler: str, seed: int, batch_size: int, points: np.ndarray | None) -> _Plan:
    """Check the settings, build the plugins and the design (the sampler's, or ``points``) with its keys."""
    from invphys.core.spec import MAX_DATASET_N

    if not 0 < n <= MAX_DATASET_N:
        raise InvphysError(f"dataset.n must be in [1, {MAX_DATASET_N:,}], got {n}")
    if batch_size <= 0:
        raise InvphysError(f"dataset.batch_size must be > 0, got {batch_size}")
    sim_block = dict(simulator)
    sim = reg.create("simulator", sim_block)
    if features is None:
        default = sim.default_feature_extractor()
        if default is None:
            raise InvphysError(f"simulator {sim.name!r} names no default feature extractor; "
                               "set a 'features' block")
        features = {"type": default}
    ext_block = dict(features)
    extractor = reg.create("feature_extractor", ext_block)
    exec_block = dict(executor or {"type": "local"})
    execu = reg.create("executor", exec_block)
    space = sim.parameter_space()
    identity = RunIdentity.of(sim)

    if points is None:
        theta = round_theta(sample_unit(n, space.dim, sampler, seed))
    else:
        theta = round_theta(np.asarray(points, dtype=np.float64))
        if theta.ndim != 2 or theta.shape[1] != space.dim or not ((theta >= 0) & (theta <= 1)).all():
            raise InvphysError(f"design points must be an (n, {space.dim}) array in [0, 1]")
    keys = row_keys(theta, identity)
    if len(set(keys)) != len(keys):
        raise InvphysError("the sampled design repeats a point at the key precision; use another seed")
    return _Plan(sim=sim, sim_block=sim_block, ext_block=ext_block, exec_block=exec_block, executor=execu,
                 extractor=extractor, space=space, identity=identity, theta=theta,
                 params=space.denormalize(theta), keys=keys)


class _Session:
    """One generation session under the store's write lock: its summary, its entry in the metadata's
    ``sessions``, and the flushes that store rows and rewrite the metadata (a flush is never cut short by
    SIGTERM or Ctrl-C: see :class:`_Stopper`)."""

    def __init__(self, store: DatasetStore, meta: dict[str, Any], summary: GenerationSummary,
                 session: dict[str, Any], prior_ok: int, prior_failed: int) -> None:
        self.store, self.meta, self.summary, self.session = store, meta, summary, session
        self.prior_ok, self.prior_failed = prior_ok, prior_failed
        self.t0 = time.monotonic()
        self.devices: set[str] = set()
        self.backends: set[str] = set()
        self.stopper = _Stopper()

    def record(self, result: Any) -> None:
        """Count one finished run."""
        summary = self.summary
        summary.ran += 1
        summary.ok += bool(result.ok)
        summary.failed = summary.ran - summary.ok
        self.devices.update([result.stats.device] if result.stats.device else [])
        self.backends.update([result.stats.backend] if result.stats.backend else [])

    def flush(self, buffer: list[Row]) -> None:
        """Store ``buffer`` (then empty it) and rewrite the metadata with this session's figures."""
        with self.stopper.critical():
            self._flush(buffer)

    def _flush(self, buffer: list[Row]) -> None:
        summary, session, meta = self.summary, self.session, self.meta
        self.store.append(buffer)
        buffer.clear()
        summary.wall_s = time.monotonic() - self.t0
        summary.devices, summary.backends = sorted(self.devices), sorted(self.backends)
        session.update(finished_at=_utcnow(), wall_s=round(summary.wall_s, 3), ran=summary.ran,
                       ok=summary.ok, failed=summary.failed, stop_reason=summary.stop_reason,
                       runs_per_hour=round(summary.runs_per_hour, 1), devices=summary.devices,
                       backends=summary.backends)
        summary.total_ok, summary.total_failed = self.prior_ok + summary.ok, self.prior_failed + summary.failed
        summary.total_rows = summary.total_ok + summary.total_failed
        sessions = meta["sessions"]
        meta["totals"] = {
            "rows": summary.total_rows, "ok": summary.total_ok, "failed": summary.total_failed,
            "generation_wall_s": round(sum(s.get("wall_s", 0.0) for s in sessions), 3),
            "devices": sorted({d for s in sessions for d in s.get("devices", [])}),
            "backends": sorted({b for s in sessions for b in s.get("backends", [])}),
        }
        self.store.write_metadata(meta)


def _open_session(store: DatasetStore, plan: _Plan, sampler: str, seed: int, batch_size: int,
                  limit_minutes: float | None, spec: dict[str, Any] | None, design: dict[str, Any] | None,
                  progress: bool, console: Any) -> tuple[_Session, np.ndarray]:
    """Create (or check) the store, find the design rows it does not hold yet (costliest first within
    windows of :data:`COST_WINDOW_BATCHES` batches) and start a
    session in its metadata. Needs the store's write lock."""
    sim, space, keys, n = plan.sim, plan.space, plan.keys, plan.n
    meta = store.create_or_check({
        "identity": plan.identity.to_dict(),
        "param_names": list(space.names),
        "feature_names": list(plan.extractor.feature_names),
        "parameter_space": space.describe(),
        "simulator": sim.describe(),
        "simulator_block": plan.sim_block,
        "extractor_block": plan.ext_block,
    })
    frame = store.frame() if store.parts() else None
    present = set(frame["key"]) if frame is not None else set()
    prior_ok = int((frame["status"] == "ok").sum()) if frame is not None else 0
    prior_failed = (len(frame) - prior_ok) if frame is not None else 0
    todo = _costliest_first(sim, plan.params, np.array([i for i, k in enumerate(keys) if k not in present],
                                                       dtype=np.int64), COST_WINDOW_BATCHES * batch_size)
    summary = GenerationSummary(path=str(store.path), requested=n, already_present=n - len(todo),
                                other_rows=len(present - set(keys)))
    if summary.other_rows and progress and design is None:
        from rich.console import Console

        (console or Console(stderr=True)).print(
            f"[yellow]note:[/] {summary.other_rows} stored rows are not points of this design "
            f"(sampler {sampler!r}, n={n}, seed={seed}); they stay in the dataset")
    session: dict[str, Any] = {
        "started_at": _utcnow(), "n": n, "sampler": sampler, "seed": seed, "batch_size": batch_size,
        "executor": plan.exec_block, "limit_minutes": limit_minutes, "host": host_info(),
        "simulator_config": sim.describe().get("config"),
        **({"design": design} if design is not None else {}),
    }
    meta["sessions"] = [*meta.get("sessions", []), session]
    if spec is not None:
        meta["spec"] = spec
    return _Session(store, meta, summary, session, prior_ok, prior_failed), todo


class _BatchClock:
    """Which of the executor's batches have come back whole, and whether the time limit stops the run: it
    stops between batches before one it expects to end after the limit, or a batch's time past the limit."""

    def __init__(self, n_todo: int, batch_size: int, t0: float, limit_minutes: float | None) -> None:
        self.batch_size, self.t0 = batch_size, t0
        self.sizes = {b: min(batch_size, n_todo - b * batch_size) for b in range(-(-n_todo // batch_size))}
        self.received: dict[int, int] = {}
        self.deadline = t0 + 60.0 * limit_minutes if limit_minutes else None
        self.batches_done = 0

    def received_row(self, local_i: int) -> None:
        b = local_i // self.batch_size
        self.received[b] = self.received.get(b, 0) + 1
        if self.received[b] == self.sizes[b]:
            del self.received[b]
            self.batches_done += 1

    def out_of_time(self, now: float) -> bool:
        if self.deadline is None:
            return False
        per_batch = (now - self.t0) / max(self.batches_done, 1)
        idle = not self.received  # no batch half-delivered
        return (idle and now + per_batch > self.deadline) or now > self.deadline + per_batch


def _simulate(plan: _Plan, run: _Session, todo: np.ndarray, batch_size: int, limit_minutes: float | None,
              flush_every_s: float, index_offset: int, progress: bool, console: Any) -> None:
    """Run the design rows ``todo`` through the executor and store them as they come back (every
    ``batch_size`` rows or ``flush_every_s`` seconds); a time limit, SIGTERM or Ctrl-C stops it cleanly
    with every finished row stored (``run.summary.stop_reason`` says why it stopped)."""
    summary, theta, params, keys = run.summary, plan.theta, plan.params, plan.keys
    n_features = len(plan.extractor.feature_names)
    clock = _BatchClock(len(todo), batch_size, run.t0, limit_minutes)
    buffer: list[Row] = []
    last_flush = time.monotonic()
    bar = _Progress(progress, console, len(todo), summary.already_present)
    runs = plan.executor.run(plan.sim_block, plan.ext_block, params[todo], batch_size)
    try:
        with run.stopper.installed(), bar:
            for local_i, result in runs:
                with run.stopper.critical():
                    i = int(todo[local_i])
                    check_features(result, n_features)
                    buffer.append(Row(key=keys[i], sample_index=index_offset + i, theta=theta[i], params=params[i],
                                      result=result))
                    run.record(result)
                    bar.advance(summary)
                    clock.received_row(local_i)
                    now = time.monotonic()
                    if len(buffer) >= batch_size or now - last_flush >= flush_every_s:
                        run.flush(buffer)
                        last_flush = now
                    if summary.ran < len(todo) and clock.out_of_time(now):
                        summary.stop_reason = "time_limit"
                        break
    except (KeyboardInterrupt, _Terminated) as exc:
        run.stopper.stopping()
        summary.stop_reason = "interrupted" if isinstance(exc, KeyboardInterrupt) else "terminated"
    except Exception:
        summary.stop_reason = "error"
        raise
    finally:
        runs_close = getattr(runs, "close", None)
        if runs_close is not None:
            runs_close()
        run.flush(buffer)


class _Progress:
    """A rich progress bar with ok/failed counts, runs per hour and ETA (a no-op when disabled)."""

    def __init__(self, enabled: bool, console: Any, total: int, skipped: int) -> None:
        self.enabled = enabled
        self.t0 = time.monotonic()
        self.progress: Any = None
        if not enabled:
            return
        from rich.console import Console
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.progress = Progress(
            TextColumn("[bold]simulating"), BarColumn(), MofNCompleteColumn(),
            TextColumn("[green]{task.fields[ok]} ok[/] [red]{task.fields[failed]} failed[/]"),
            TextColumn("{task.fields[rate]} runs/h"), TimeElapsedColumn(), TextColumn("ETA"),
            TimeRemainingColumn(), console=console or Console(stderr=True), transient=False,
        )
        self.task = self.progress.add_task("simulate", total=total, ok=0, failed=0, rate="-")
        if skipped:
            self.progress.console.print(f"resuming: {skipped} rows already stored, {total} to run")

    def __enter__(self) -> _Progress:
        if self.progress is not None:
            self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.progress is not None:
            self.progress.stop()

    def advance(self, summary: GenerationSummary) -> None:
        if self.progress is None:
            return
        elapsed = time.monotonic() - self.t0
        rate = f"{3600.0 * summary.ran / elapsed:,.0f}" if elapsed > 0 else "-"
        self.progress.update(self.task, advance=1, ok=summary.ok, failed=summary.failed, rate=rate)


def generate_from_spec(spec: Any, out: str | os.PathLike[str] | None = None, progress: bool = True,
                       console: Any = None, registry: Any = None,
                       limit_minutes: float | None = None) -> GenerationSummary:
    """Generate the dataset an :class:`~invphys.core.spec.ExperimentSpec` describes into ``out``
    (default: ``dataset.path``). ``limit_minutes`` overrides ``dataset.limit_minutes``."""
    ds = spec.dataset
    target = out if out is not None else ds.path
    if target is None:
        raise InvphysError("no output directory: pass --out or set dataset.path in the spec")
    return generate_dataset(
        Path(target), simulator=spec.simulator, features=spec.features, executor=spec.executor, n=ds.n,
        sampler=ds.sampler, batch_size=ds.batch_size, seed=ds.seed if ds.seed is not None else spec.seed,
        limit_minutes=limit_minutes if limit_minutes is not None else ds.limit_minutes,
        spec=spec.model_dump(mode="json", by_alias=True), progress=progress, console=console,
        registry=registry, adaptive=ds.adaptive,
    )
