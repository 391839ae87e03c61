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
from invphys.core.results import RunStats, ValidationRecord


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

    class Config(PluginConfig):
        overrides: dict[str, Any] = Field(default_factory=dict,
                                          description="simulator config keys to change for validation")
        kappa: float = Field(3.0, gt=0, description="sharpness of R_gt")
        batch_size: int = Field(16, ge=1, description="parameter vectors per simulator call")

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
                          on_run: Callable[[int], None] | None = None) -> SimulatedFeatures:
        """Simulate rows of ``theta`` (B, d) in [0, 1]^d and extract their features (NaN rows on failure).

        ``keep_trajectories``: True keeps every successful run's trajectory, a collection of row indices
        keeps only those (trajectories can be large), False none. ``on_run(row)`` is called as each
        run finishes (progress bars).
        """
        sim = self.simulator_for(simulator)
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        params = sim.parameter_space().denormalize(theta)
        m = len(extractor.feature_names)
        out = np.full((len(theta), m), np.nan)
        failures: list[str | None] = [None] * len(theta)
        stats: list[RunStats | None] = [None] * len(theta)
        trajs: list[Any] = [None] * len(theta)
        bs = self.config.batch_size
        for start in range(0, len(theta), bs):
            rows = list(range(start, min(start + bs, len(theta))))
            try:
                results = sim.simulate(params[rows], on_result=None if on_run is None else
                                       lambda i, _res, rows=rows: on_run(rows[i]))
            except SimulationFailed:
                results = []
                for r in rows:  # isolate the failing row(s)
                    try:
                        results += sim.simulate(params[r:r + 1])
                    except SimulationFailed as exc:
                        results.append(exc)
            for r, res in zip(rows, results, strict=True):
                if isinstance(res, SimulationFailed):
                    failures[r] = res.reason
                    continue
                stats[r] = res.stats
                if not res.ok:
                    failures[r] = res.failure or "simulation failed"
                    continue
                try:
                    feats = res.features if res.features is not None else extractor.extract(res.trajectory)
                except SimulationFailed as exc:
                    failures[r] = exc.reason
                    continue
                feats = np.asarray(feats, dtype=np.float64).reshape(-1)
                if feats.shape != (m,) or not np.all(np.isfinite(feats)):
                    failures[r] = f"feature extraction gave {feats.shape} / non-finite features"
                    continue
                out[r] = feats
                if keep_trajectories is True or (keep_trajectories and r in keep_trajectories):
                    trajs[r] = res.trajectory
        return SimulatedFeatures(out, failures, stats, trajs)

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
