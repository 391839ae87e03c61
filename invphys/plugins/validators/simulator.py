"""The ``simulator`` validator (paper sec. 3.6): re-run theta* through the real simulator."""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError, SimulationFailed
from invphys.core.interfaces import FeatureExtractor, PluginConfig, Simulator, Validator
from invphys.core.objectives import recovery_reward
from invphys.core.results import RunStats, SimulationResult, ValidationRecord
from invphys.core.stream import stream_until_broken, unreturned
from invphys.plugins.executors import _deadline
from invphys.plugins.executors._extract_pool import DEFAULT_TIMEOUT_S


@dataclass
class SimulatedFeatures:
    """Features of re-simulated parameters: ``features`` (B, M) with NaN rows where a run failed."""

    features: np.ndarray
    failures: list[str | None]
    stats: list[RunStats | None]
    trajectories: list[Any]


class SimulatorValidator(Validator):
    """Re-simulates normalised parameters, extracts features and scores them with R_gt (eq. 1).

    For each row: ``r_surrogate = R_gt(predicted, target)``, ``r_actual = R_gt(actual, target)``,
    ``gap = r_surrogate - r_actual``. ``overrides`` are merged into the simulator's config before
    validating (e.g. ``{backend: warp, preset: small}``) so that validation can run another backend or
    preset than dataset generation. Failed runs give ``r_actual = NaN`` and their ``failure`` reason.
    """

    name: ClassVar[str] = "simulator"
    #: settings that change how fast validation goes, not its results: left out of the stage keys
    identity_ignores: ClassVar[tuple[str, ...]] = ("batch_size", "extract_workers", "extract_timeout_s")

    class Config(PluginConfig):
        overrides: dict[str, Any] = Field(default_factory=dict,
                                          description="simulator config keys to change for validation")
        kappa: float = Field(3.0, gt=0, description="sharpness of R_gt")
        batch_size: int = Field(16, ge=1, description="runs in flight on a simulator with a continuous-batching "
                                                      "stream (else parameter vectors per simulator call)")
        extract_workers: int = Field(0, ge=0, le=256,
                                     description="extract features in this many worker processes while the "
                                                 "simulator goes on (0: in the simulator's thread)")
        extract_timeout_s: float | None = Field(
            DEFAULT_TIMEOUT_S, gt=0, description="seconds one run's feature extraction may take (in this thread "
                                                 "or an extraction process) before the run is a recorded "
                                                 "failure (None: no limit)")

    def simulator_for(self, simulator: Simulator) -> Simulator:
        """``simulator`` itself, or a copy with ``overrides`` applied (validated by its Config)."""
        if not self.config.overrides:
            return simulator
        settings = {**simulator.config.model_dump(), **self.config.overrides}
        try:
            return type(simulator)(type(simulator).Config(**settings))
        except Exception as exc:  # pydantic ValidationError -> user error
            raise InvphysError(f"validator.overrides do not fit simulator {simulator.name!r}: {exc}") from exc

    def simulate_features(self, theta: np.ndarray, simulator: Simulator, extractor: FeatureExtractor,
                          keep_trajectories: bool | Collection[int] = False,
                          on_run: Callable[[int], None] | None = None,
                          on_record: Callable[[int, np.ndarray | None, str | None, RunStats | None], None] | None = None
                          ) -> SimulatedFeatures:
        """Simulate rows of ``theta`` (B, d) in [0, 1]^d and extract their features (NaN rows on failure).

        ``keep_trajectories``: True keeps every successful run's trajectory, a collection of row indices
        keeps only those (trajectories can be large), False none. ``on_run(row)`` is called as each
        run finishes (progress bars). ``on_record(row, features or None, failure, stats)`` is called once
        per row as soon as its outcome is known: as the run finishes when the simulator reports runs one by
        one (``on_result``), else when its batch returns (a caller that stores rows loses no finished run).
        A simulator with its own continuous-batching stream (``native_stream``: the AnisoMPM foods) runs
        every row in one stream of ``batch_size`` slots, as dataset generation does, so no chunk waits on
        its slowest run; the others (and the rows of a stream that raised) go in chunks of ``batch_size``.
        """
        sim = self.simulator_for(simulator)
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        params = sim.parameter_space().denormalize(theta)
        m = len(extractor.feature_names)
        out = np.full((len(theta), m), np.nan)
        failures: list[str | None] = [None] * len(theta)
        stats: list[RunStats | None] = [None] * len(theta)
        trajs: list[Any] = [None] * len(theta)
        settled: set[int] = set()
        pool = self._pool(extractor)
        pending: dict[int, tuple[Any, Any]] = {}  # row -> (result, future of its features): in a worker

        def keep(r: int) -> bool:
            return keep_trajectories is True or bool(keep_trajectories and r in keep_trajectories)

        def settle(r: int, res: Any, fut: Any = None) -> None:
            """Row ``r``'s features, failure, stats (and trajectory) from its result, recorded once."""
            if r in settled:
                return
            settled.add(r)
            feats, failures[r], stats[r] = self._outcome(res, extractor, m, fut, self.config.extract_timeout_s)
            if feats is not None:
                out[r] = feats
            if failures[r] is None and keep(r):
                trajs[r] = res.trajectory
            if on_record is not None:
                on_record(r, out[r].copy() if failures[r] is None else None, failures[r], stats[r])

        def collect(wait: bool) -> None:
            for r in [r for r, (_, fut) in pending.items() if wait or fut.done()]:
                res, fut = pending.pop(r)
                settle(r, res, fut)

        def finished(r: int, res: Any) -> None:
            if pool is not None and r not in settled and r not in pending and isinstance(res, SimulationResult) \
                    and res.ok and res.features is None and res.trajectory is not None:
                pending[r] = (res, pool.extract(res.trajectory))
                if not keep(r):
                    res.trajectory = None
                collect(False)
            else:
                settle(r, res)
            if on_run is not None:
                on_run(r)

        bs = self.config.batch_size
        left = list(range(len(theta)))
        if getattr(sim, "native_stream", False):
            left = self._streamed(sim, params, bs, finished)
            collect(True)   # the streamed rows' features still in the extraction workers
        for start in range(0, len(left), bs):
            rows = left[start:start + bs]
            results = self._chunk(sim, params, rows, finished, lambda r: r in settled or r in pending)
            collect(True)
            for r, res in zip(rows, results, strict=True):
                if res is not None:
                    settle(r, res)
        return SimulatedFeatures(out, failures, stats, trajs)

    @staticmethod
    def _chunk(sim: Simulator, params: np.ndarray, rows: list[int], finished: Callable[[int, Any], None],
               reported: Callable[[int], bool]) -> list[Any]:
        """One :meth:`Simulator.simulate` call on ``rows`` (each run handed to ``finished(row, result)`` as it
        ends); if it raises :class:`SimulationFailed`, the rows not ``reported`` yet are re-run one by one, a
        failing row giving its exception. Returns one result (or exception, or None: reported) per row."""
        try:
            return sim.simulate(params[rows], on_result=lambda i, res: finished(rows[i], res))
        except SimulationFailed:
            results: list[Any] = []
            for r in rows:  # isolate the failing row(s); rows already reported keep their outcome
                if reported(r):
                    results.append(None)
                    continue
                try:
                    results += sim.simulate(params[r:r + 1])
                except SimulationFailed as exc:
                    results.append(exc)
            return results

    @staticmethod
    def _streamed(sim: Simulator, params: np.ndarray, slots: int, finished: Callable[[int, Any], None]) -> list[int]:
        """Run every row through the simulator's continuous-batching stream (``slots`` runs in flight, the next
        row starting as soon as one ends, as dataset generation runs them), handing each result to
        ``finished(row, result)``; return the rows it did not return (the stream raised, a run that blew up
        or a device error, or ended short), which then go through :meth:`Simulator.simulate` in chunks, a failing row alone."""
        seen: set[int] = set()
        for i, res in stream_until_broken(sim, params, slots, seen):
            finished(i, res)   # what this raises is the caller's, as on the chunked path
        return unreturned(len(params), seen)

    def _pool(self, extractor: FeatureExtractor) -> Any:
        """The worker processes of ``extract_workers`` (None: extract in this thread), kept for later calls
        with the same extractor."""
        if not self.config.extract_workers:
            return None
        from invphys.plugins.executors._extract_pool import ExtractionPool

        key = (type(extractor).__module__, type(extractor).__qualname__,
               extractor.config.model_dump_json() if getattr(extractor, "config", None) is not None else "")
        pools = self.__dict__.setdefault("_pools", {})
        if key not in pools:
            pools[key] = ExtractionPool(extractor, self.config.extract_workers,
                                         timeout_s=self.config.extract_timeout_s)
        return pools[key]

    @staticmethod
    def _outcome(res: Any, extractor: FeatureExtractor, m: int, fut: Any = None,
                 timeout_s: float | None = DEFAULT_TIMEOUT_S) -> tuple[np.ndarray | None, str | None, RunStats | None]:
        """One result's (features or None, failure reason or None, stats); ``fut``: its features are being
        extracted in a worker process (what the extractor raised there is raised here), else they are
        extracted here within ``timeout_s`` (:mod:`invphys.plugins.executors._deadline`)."""
        if isinstance(res, SimulationFailed):
            return None, res.reason, None
        if not res.ok:
            return None, res.failure or "simulation failed", res.stats
        try:
            if fut is not None:
                feats = fut.result()
            else:
                feats = (res.features if res.features is not None
                         else _deadline.call(extractor.extract, timeout_s, res.trajectory))
        except SimulationFailed as exc:
            return None, exc.reason, res.stats
        feats = np.asarray(feats, dtype=np.float64).reshape(-1)
        if feats.shape != (m,) or not np.all(np.isfinite(feats)):
            return None, f"feature extraction gave {feats.shape} / non-finite features", res.stats
        return feats, None, res.stats

    def validate(self, theta: np.ndarray, targets: np.ndarray, predicted: np.ndarray,
                 simulator: Simulator, extractor: FeatureExtractor,
                 scales: np.ndarray) -> list[ValidationRecord]:
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        sim = self.simulate_features(theta, simulator, extractor)
        return self.records(theta, targets, predicted, sim, scales)

    def records(self, theta: np.ndarray, targets: np.ndarray, predicted: np.ndarray,
                sim: SimulatedFeatures, scales: np.ndarray) -> list[ValidationRecord]:
        """Score already simulated features (``sim`` from :meth:`simulate_features`) against ``targets``."""
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        targets = np.atleast_2d(np.asarray(targets, dtype=np.float64))
        predicted = np.atleast_2d(np.asarray(predicted, dtype=np.float64))
        if not len(theta) == len(targets) == len(predicted) == len(sim.features):
            raise InvphysError(f"validate: {len(theta)} theta rows, {len(targets)} targets and "
                               f"{len(predicted)} predictions differ in number")
        kappa = self.config.kappa
        r_surr = recovery_reward(predicted, targets, scales, kappa)
        records = []
        for i in range(len(theta)):
            ok = sim.failures[i] is None
            r_act = float(recovery_reward(sim.features[i], targets[i], scales, kappa)) if ok else float("nan")
            records.append(ValidationRecord(
                theta=theta[i], target=targets[i], predicted=predicted[i],
                actual=sim.features[i] if ok else None, r_surrogate=float(r_surr[i]), r_actual=r_act,
                gap=float(r_surr[i]) - r_act, failure=sim.failures[i], stats=sim.stats[i]))
        return records
