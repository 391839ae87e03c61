"""The plugin interfaces: what a simulator, feature extractor, surrogate, latent model, optimiser,
validator and executor must provide.

Every plugin class:

* has a class attribute ``name`` (unique per kind; what a spec's ``type:`` field names),
* has a nested pydantic ``Config`` (``extra="forbid"``) describing its settings; the spec block of a
  plugin is validated by it, and ``invphys schema`` publishes it,
* is constructed as ``Plugin(config)`` or ``Plugin(**settings)``.

Arrays follow one convention: ``theta`` is normalised parameters in [0, 1]^d (shape (B, d)),
``params`` is physical parameters in the simulator's units (shape (B, d)), ``y`` is features (B, M),
``z`` latent codes (B, k). Heavy libraries (torch, taichi, warp, stable-baselines3) are imported
inside methods, never at module top level, so that listing plugins stays fast.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from invphys.core.params import ParameterSpace
from invphys.core.results import (
    DEFAULT_MAX_FRAMES,
    OptimizationResult,
    Rendering,
    SimulationResult,
    Trajectory,
    ValidationRecord,
)


class PluginConfig(BaseModel):
    """Base of every plugin's ``Config``: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=False)


class Plugin(ABC):
    """Common base: a ``name``, a ``kind`` and a validated ``config``."""

    name: ClassVar[str]
    kind: ClassVar[str]
    Config: ClassVar[type[PluginConfig]] = PluginConfig
    #: the validated settings (an instance of the subclass's own ``Config``)
    config: Any

    def __init__(self, config: PluginConfig | dict[str, Any] | None = None, **settings: Any) -> None:
        if config is None:
            config = self.Config(**settings)
        elif isinstance(config, dict):
            config = self.Config(**{**config, **settings})
        elif settings:
            config = config.model_copy(update=settings)
        self.config = config

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config!r})"


# --------------------------------------------------------------------------------------------
# Simulation
# --------------------------------------------------------------------------------------------
class Simulator(Plugin):
    """A (typically expensive, non-differentiable) simulator mapping parameters to trajectories.

    Subclasses define :meth:`parameter_space` and :meth:`simulate`. A simulator simulates a *batch*
    of physical parameter vectors in one call so that a GPU backend can advance all of them at once.
    A run that blows up is returned with ``ok=False`` and a ``failure`` reason, never as data.
    """

    kind: ClassVar[str] = "simulator"
    #: Version string recorded with every run and part of its stored identity: bump it whenever the
    #: same parameters and config can give different results (physics, numerics, features' inputs).
    version: ClassVar[str] = "0"
    #: Config fields that change where or how fast runs go but not their results (device, batch size):
    #: left out of the config hash in a run's stored identity. Every other field counts.
    identity_ignores: ClassVar[tuple[str, ...]] = ()

    @abstractmethod
    def parameter_space(self) -> ParameterSpace:
        """The parameters this simulator takes, in order, with their physical ranges."""

    @abstractmethod
    def simulate(self, params: np.ndarray,
                 on_result: Callable[[int, SimulationResult], None] | None = None) -> list[SimulationResult]:
        """Simulate each row of ``params`` (B, d) (physical units, checked against the ranges).

        Returns one :class:`SimulationResult` per row, in order. ``on_result(i, result)`` is called as
        soon as row ``i`` finishes so that callers can store results before the batch ends.
        Raises :class:`~invphys.core.errors.ParameterRangeError` for out-of-range input.
        """

    def default_feature_extractor(self) -> str | None:
        """The name of the feature extractor that fits this simulator's trajectories, if any."""
        return None

    def estimate_cost(self, params: np.ndarray) -> np.ndarray | None:
        """Optional: the relative cost of each row of ``params`` (n, d), e.g. its time steps, from cheap
        host arithmetic. Dataset generation then starts the costliest runs first, so each batch holds
        runs of similar cost (a lock-step batch waits for its slowest run). None: design order."""
        return None

    #: True when :meth:`simulate_stream` keeps the device busy across the whole stream (continuous
    #: batching: a finished run's slot takes the next row at once); executors then hand it all their rows.
    native_stream: ClassVar[bool] = False

    def simulate_stream(self, params: np.ndarray, batch_size: int | None = None
                        ) -> Iterator[tuple[int, SimulationResult]]:
        """Yield ``(i, result)`` for each row ``i`` of ``params`` (n, d) as it finishes, in any order.

        Optional: a simulator with a warm device engine overrides it (and sets :attr:`native_stream`) to
        keep ``batch_size`` runs in flight and start the next row as soon as one ends. This default
        calls :meth:`simulate` on consecutive chunks of ``batch_size`` rows (all rows if None).
        """
        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        step = max(1, int(batch_size or len(params) or 1))
        for start in range(0, len(params), step):
            for j, res in enumerate(self.simulate(params[start:start + step])):
                yield start + j, res

    #: True when :meth:`simulate_feed` takes new rows into slots as they free while other runs go on (an
    #: open continuous-batching stream); False: the default below, which simulates what is ready in chunks.
    native_feed: ClassVar[bool] = False

    def simulate_feed(self, feeder: Callable[[int], np.ndarray | None], batch_size: int | None = None
                      ) -> Iterator[tuple[int, SimulationResult]]:
        """An open stream: yield ``(i, result)`` for rows that ``feeder`` hands in while earlier rows run.

        ``feeder(free)`` is called whenever up to ``free`` runs could start and returns new rows (k, d) of
        physical parameters (k may exceed ``free``: the rest wait), or None / no rows when no work is ready
        yet. ``i`` counts fed rows from 0 in the order they were fed; results come in any order. The
        stream ends when the feeder has nothing while no run is in flight and every result was handed
        out. This default asks for ``batch_size`` rows (None: all that are ready), simulates them through
        :meth:`simulate_stream` and asks again when they are done; a chunk that raises
        :class:`~invphys.core.errors.SimulationFailed` is re-run row by row, a failing row giving a failed
        result. A simulator with a warm device engine overrides it (and sets :attr:`native_feed`).
        """
        from invphys.core.errors import SimulationFailed

        ask = int(batch_size) if batch_size else 1 << 30
        fed = 0
        while True:
            rows = feeder(ask)
            rows = np.empty((0, 0)) if rows is None else np.atleast_2d(np.asarray(rows, dtype=np.float64))
            if rows.size == 0:
                return
            done: set[int] = set()
            try:
                for j, res in self.simulate_stream(rows, batch_size):
                    done.add(j)
                    yield fed + j, res
            except SimulationFailed:
                for j in range(len(rows)):
                    if j not in done:
                        yield fed + j, self._one_or_failure(rows[j])
            fed += len(rows)

    def _one_or_failure(self, row: np.ndarray) -> SimulationResult:
        """One row simulated alone; a :class:`SimulationFailed` becomes a failed result."""
        from invphys.core.errors import SimulationFailed
        from invphys.core.results import RunStats

        try:
            return self.simulate(row[None, :])[0]
        except SimulationFailed as exc:
            return SimulationResult(params=row, ok=False, stats=RunStats(simulator=self.name,
                                                                          simulator_version=self.version),
                                    failure=exc.reason)

    def describe(self) -> dict[str, Any]:
        """Provenance recorded with datasets (name, version, config)."""
        return {"simulator": self.name, "version": self.version, "config": self.config.model_dump()}

    def render(self, trajectory: Trajectory, path: str | Path, *, max_frames: int = DEFAULT_MAX_FRAMES,
               animation: str = "gif", **options: Any) -> Rendering:
        """Draw ``trajectory`` into the directory ``path``; optional, override it to draw your own.

        Used by ``invphys simulate --render``, ``invphys render`` and the report (which asks for
        ``max_frames=1``: the final state). Write at most ``max_frames`` frame images (evenly spread,
        ending on the last frame: :func:`~invphys.core.results.frame_selection`), plus at most one
        summary image; ``animation`` is ``"gif"``, ``"mp4"`` or ``"none"``. ``options`` are your own
        keyword settings (``invphys render --option key=value``); reject ones you do not know with an
        :class:`~invphys.core.errors.InvphysError`.

        This default draws particle frames as x-y scatters coloured by damage and plots every time
        series (:func:`invphys.core.trajectory_plot.render_trajectory`); it takes no ``options``.
        """
        if options:
            from invphys.core.errors import InvphysError

            raise InvphysError(f"simulator {self.name!r} renders with the generic renderer, which takes no "
                               f"options (got {', '.join(sorted(options))})")
        from invphys.core.trajectory_plot import render_trajectory

        return render_trajectory(trajectory, path, max_frames=max_frames, animation=animation, title=self.name)


class FeatureExtractor(Plugin):
    """Turns a :class:`Trajectory` into a fixed-length behavioural feature vector.

    Subclasses define :attr:`feature_names` and :meth:`extract`. Optional:

    * ``feature_units``: a property or class attribute giving each feature's unit, a tuple of strings in
      :attr:`feature_names`' order (or a mapping ``{name: unit}``; ``""`` for dimensionless or unknown,
      e.g. ``("N", "s", "")``). Bundles record them, and ``invphys invert``, its JSON and the Python
      :class:`~invphys.inverter.InversionResult` show them beside each value. Without it every unit is ``""``.
    * ``version``: a class attribute string, like :attr:`Simulator.version`; bump it when the same
      trajectory gives other features.

    The pipeline's stage keys hold the extractor's registered name, ``version``, config, feature names and
    units (``invphys.pipeline.cache.extractor_identity``): changing any of them re-runs the stages that
    record them (the dataset stage, which then finds every run stored, and those after it).
    """

    kind: ClassVar[str] = "feature_extractor"

    @property
    @abstractmethod
    def feature_names(self) -> tuple[str, ...]:
        """Names of the M features, in output order."""

    @abstractmethod
    def extract(self, trajectory: Trajectory) -> np.ndarray:
        """Features (M,) float64 of one trajectory; every entry finite (degenerate runs handled)."""

    def extract_many(self, trajectories: Sequence[Trajectory]) -> np.ndarray:
        """Features (B, M) of several trajectories."""
        return np.stack([self.extract(t) for t in trajectories])


class Executor(Plugin):
    """Runs batches of simulations somewhere (in-process, a process pool, a Ray cluster).

    Executors yield results as they complete; callers store each result at once so that a killed run
    loses at most the batches in flight.
    """

    kind: ClassVar[str] = "executor"

    @abstractmethod
    def run(self, simulator_spec: dict[str, Any], extractor_spec: dict[str, Any] | None,
            params: np.ndarray, batch_size: int) -> Iterator[tuple[int, SimulationResult]]:
        """Yield ``(row_index, result)`` for every row of ``params`` (B, d), in completion order.

        ``simulator_spec``/``extractor_spec`` are ``{"type": name, **config}`` blocks so that remote
        workers can rebuild the plugins. When an extractor is given, results carry ``features`` and
        no trajectory (bounded memory).
        """


# --------------------------------------------------------------------------------------------
# Learning
# --------------------------------------------------------------------------------------------
class Persistent(Plugin):
    """A trainable plugin that saves to and loads from a directory, with config and metrics."""

    #: metrics of the last fit (e.g. {"r2": 0.93, "r2_per_feature": [...]})
    metrics: dict[str, Any]

    @abstractmethod
    def save(self, directory: str | Path) -> Path:
        """Write weights, config, data fingerprint and metrics under ``directory``; return it."""

    @classmethod
    @abstractmethod
    def load(cls, directory: str | Path) -> Persistent:
        """Rebuild a fitted model saved by :meth:`save` (identical predictions)."""


class Surrogate(Persistent):
    """A fast model of the simulator's features: theta in [0,1]^d -> y in R^M."""

    kind: ClassVar[str] = "surrogate"

    @abstractmethod
    def fit(self, theta: np.ndarray, y: np.ndarray, progress: bool = False) -> dict[str, Any]:
        """Train on (N, d) normalised parameters and (N, M) features; return metrics."""

    @abstractmethod
    def predict(self, theta: np.ndarray) -> np.ndarray:
        """Predicted features (B, M) for (B, d) normalised parameters (batched, no gradients)."""

    def predict_with_uncertainty(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(mean, std), both (B, M). Surrogates without uncertainty return a zero std."""
        mean = self.predict(theta)
        return mean, np.zeros_like(mean)


class LatentModel(Persistent):
    """A learned low-dimensional code z for normalised parameters, with an optional feature head."""

    kind: ClassVar[str] = "latent_model"
    #: the box the latent search space uses (paper: [-3, 3]^4)
    latent_bound: ClassVar[float] = 3.0

    @property
    @abstractmethod
    def latent_dim(self) -> int:
        """Dimension k of the latent code."""

    @abstractmethod
    def fit(self, theta: np.ndarray, y: np.ndarray, progress: bool = False) -> dict[str, Any]:
        """Train on (N, d) normalised parameters and (N, M) features; return metrics."""

    @abstractmethod
    def encode(self, theta: np.ndarray) -> np.ndarray:
        """Deterministic latent codes (B, k) (the mean for a VAE)."""

    @abstractmethod
    def decode(self, z: np.ndarray) -> np.ndarray:
        """Normalised parameters (B, d), clipped to [0, 1]."""

    def predict_features(self, z: np.ndarray) -> np.ndarray:
        """The model's own feature head, (B, M) (the paper's "own head" ablation)."""
        raise NotImplementedError(f"latent model {self.name!r} has no feature head")


# --------------------------------------------------------------------------------------------
# Optimisation and validation
# --------------------------------------------------------------------------------------------
@dataclass
class SearchSpace:
    """Where an optimiser searches: a box, and how its points become normalised parameters.

    The raw space is [0, 1]^d with the identity; a latent space is [-b, b]^k with a model's decoder.
    """

    name: str
    dim: int
    low: float
    high: float
    to_theta: Callable[[np.ndarray], np.ndarray]
    from_theta: Callable[[np.ndarray], np.ndarray] | None = None

    def clip(self, points: np.ndarray) -> np.ndarray:
        return np.clip(points, self.low, self.high)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return rng.uniform(self.low, self.high, size=(n, self.dim))


@dataclass
class Problem:
    """One optimisation problem handed to :meth:`Optimizer.optimize`.

    ``evaluate(points)`` maps (B, dim) search points to scores (B,) and counts evaluations;
    ``predict(points)`` gives the features (B, M) behind the scores. ``target`` is set for recovery
    problems (the goal a goal-conditioned policy observes).
    """

    space: SearchSpace
    predict: Callable[[np.ndarray], np.ndarray]
    objective: Callable[[np.ndarray], np.ndarray]
    budget: int
    target: np.ndarray | None = None
    initial: np.ndarray | None = None
    seed: int = 0
    info: dict[str, Any] = field(default_factory=dict)

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Scores (B,) of (B, dim) search points (clipped to the space first)."""
        return np.asarray(self.objective(self.predict(self.space.clip(np.atleast_2d(points)))))


class Optimizer(Plugin):
    """Finds search points that maximise a :class:`Problem`'s objective within its budget.

    Goal-conditioned optimisers (``goal_conditioned = True``) are trained once by :meth:`prepare` on
    a distribution of targets and then answer each :meth:`optimize` call in a few evaluations.
    """

    kind: ClassVar[str] = "optimizer"
    goal_conditioned: ClassVar[bool] = False

    def prepare(self, space: SearchSpace, predict: Callable[[np.ndarray], np.ndarray],
                train_targets: np.ndarray, scales: np.ndarray, progress: bool = False) -> dict[str, Any]:
        """Train before use (goal-conditioned optimisers); others need nothing. Returns metrics."""
        return {}

    @abstractmethod
    def optimize(self, problem: Problem) -> OptimizationResult:
        """Maximise ``problem``'s objective; never spend more than ``problem.budget`` evaluations."""


class Validator(Plugin):
    """Re-runs recovered parameters through the real simulator and scores them (paper sec. 3.6)."""

    kind: ClassVar[str] = "validator"

    @abstractmethod
    def validate(self, theta: np.ndarray, targets: np.ndarray, predicted: np.ndarray,
                 simulator: Simulator, extractor: FeatureExtractor,
                 scales: np.ndarray) -> list[ValidationRecord]:
        """One :class:`ValidationRecord` per row of ``theta`` (B, d) and ``targets`` (B, M)."""


#: The kinds of plugin, mapped to their base class (the registry's table of contents).
PLUGIN_KINDS: dict[str, type[Plugin]] = {
    "simulator": Simulator,
    "feature_extractor": FeatureExtractor,
    "executor": Executor,
    "surrogate": Surrogate,
    "latent_model": LatentModel,
    "optimizer": Optimizer,
    "validator": Validator,
}
