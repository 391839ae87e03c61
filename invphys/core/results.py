"""Plain data passed between pipeline stages: trajectories, simulation results, optimisation results.

These are light dataclasses over NumPy arrays, so that every stage can be tested and stored without
importing a simulator backend or torch. ``docs/api/results.md`` documents every field.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class TimeSeries:
    """One named quantity of a run over simulated time (a force, an energy, a displacement).

    Attributes:
        times: (T,) float64 simulated time in seconds of each sample, non-decreasing. Each series has
            its own time axis: a force sampled every frame and an energy sampled every substep can
            live in one trajectory.
        values: (T,) or (T, K) float array; ``values[i]`` is the quantity at ``times[i]`` (K
            components, e.g. a 3-D force).
        unit: physical unit of ``values`` (``"N"``, ``"m"``, ``"J"``; ``""`` for dimensionless).
        description: one line, used as a plot title and in docs.
    """

    times: np.ndarray
    values: np.ndarray
    unit: str = ""
    description: str = ""

    def __post_init__(self) -> None:
        self.times = np.asarray(self.times, dtype=np.float64)
        self.values = np.asarray(self.values)
        if self.times.ndim != 1:
            raise ValueError(f"TimeSeries.times must be 1-D (T,), got shape {self.times.shape}")
        if self.values.ndim not in (1, 2) or len(self.values) != len(self.times):
            raise ValueError(f"TimeSeries.values must be (T,) or (T, K) with T = {len(self.times)}, "
                             f"got shape {self.values.shape}")
        if len(self.times) > 1 and np.any(np.diff(self.times) < 0):
            raise ValueError("TimeSeries.times must be non-decreasing")

    def __len__(self) -> int:
        return len(self.times)

    def at(self, t: float | np.ndarray) -> np.ndarray:
        """Values linearly interpolated at time(s) ``t`` (1-D series only)."""
        if self.values.ndim != 1:
            raise ValueError("TimeSeries.at interpolates 1-D series only")
        return np.asarray(np.interp(t, self.times, self.values.astype(np.float64)))


@dataclass(kw_only=True)
class Trajectory:
    """What a simulator recorded in one run: named time series and/or particle frames.

    A trajectory holds *time series* (any model: lumped, FEM, MPM), *particle frames* (particle
    methods), or both. All arguments are keywords.

    Attributes:
        series: named :class:`TimeSeries` (e.g. ``{"force": TimeSeries(t, f, unit="N")}``). Feature
            extractors read them; validation keeps them whole and reports plot them.
        positions: (T, N, 3) float32 particle positions at the recorded frames, or None for a model
            without particles.
        damage: (T, N) float32 damage in [0, 1] (0 = intact) at the recorded frames, or None.
        labels: (N,) int8 region label of every particle (meaning defined by the simulator,
            e.g. skin and interior), or None.
        fields: further named per-particle arrays at the recorded frames, (T, N) or (T, N, K)
            (e.g. ``{"stress": ...}``).
        frame_indices: (T,) int indices of the recorded frames in the full frame sequence
            (required with particle frames).
        fps: frames per second of the full frame sequence (time of frame k is k / fps; required with
            particle frames).
        extra: simulator-specific scalars or arrays (e.g. a gripper path, the grid spacing). Not
            interpreted by the framework; arrays and JSON scalars survive trajectory files, other
            objects do not. Prefer ``series`` for anything that varies in time.
    """

    series: dict[str, TimeSeries] = field(default_factory=dict)
    positions: np.ndarray | None = None
    damage: np.ndarray | None = None
    labels: np.ndarray | None = None
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    frame_indices: np.ndarray | None = None
    fps: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def check(self) -> Trajectory:
        """Raise ValueError naming the first inconsistent shape or missing field; return self.

        Construction does not check (feature extractors may be handed odd data and must say so
        themselves); :func:`invphys.testing.check_simulator` and the trajectory file writer do.
        """
        for name, s in self.series.items():
            if not isinstance(s, TimeSeries):
                raise ValueError(f"Trajectory.series[{name!r}] must be a TimeSeries, got {type(s).__name__}")
        if self.positions is None:
            if self.damage is not None or self.labels is not None or self.fields:
                raise ValueError("Trajectory: damage, labels and fields need particle positions")
            return self
        pos = self.positions
        if pos.ndim != 3 or pos.shape[2] != 3:
            raise ValueError(f"Trajectory.positions must be (T, N, 3), got shape {pos.shape}")
        t, n = pos.shape[:2]
        if self.frame_indices is None or self.fps is None or not self.fps > 0:
            raise ValueError("Trajectory with particle positions needs frame_indices and fps > 0")
        if np.shape(self.frame_indices) != (t,):
            raise ValueError(f"Trajectory.frame_indices must be ({t},), got {np.shape(self.frame_indices)}")
        if self.damage is not None and self.damage.shape != (t, n):
            raise ValueError(f"Trajectory.damage must be ({t}, {n}), got {self.damage.shape}")
        if self.labels is not None and self.labels.shape != (n,):
            raise ValueError(f"Trajectory.labels must be ({n},), got {self.labels.shape}")
        for name, arr in self.fields.items():
            if arr.ndim not in (2, 3) or arr.shape[:2] != (t, n):
                raise ValueError(f"Trajectory.fields[{name!r}] must be ({t}, {n}) or ({t}, {n}, K), "
                                 f"got {arr.shape}")
        return self

    # -- particle frames -------------------------------------------------------------------------
    @property
    def has_particles(self) -> bool:
        """True when the trajectory holds particle frames."""
        return self.positions is not None

    @property
    def n_frames(self) -> int:
        """Number of recorded particle frames (0 without particles)."""
        return 0 if self.positions is None else int(self.positions.shape[0])

    @property
    def n_particles(self) -> int:
        """Number of particles (0 without particles)."""
        return 0 if self.positions is None else int(self.positions.shape[1])

    def times(self) -> np.ndarray:
        """Simulated time in seconds of each recorded particle frame (empty without particles)."""
        if self.frame_indices is None or not self.fps:
            return np.zeros(0)
        return np.asarray(self.frame_indices, dtype=np.float64) / self.fps

    def select_frames(self, index: Sequence[int] | np.ndarray) -> Trajectory:
        """A copy with only the particle frames at positions ``index``; series and ``extra`` whole."""
        if self.positions is None:
            return replace(self, series=dict(self.series), extra=dict(self.extra))
        idx = np.asarray(index, dtype=np.int64)
        return replace(self, positions=self.positions[idx],
                       damage=None if self.damage is None else self.damage[idx],
                       fields={k: v[idx] for k, v in self.fields.items()},
                       frame_indices=np.asarray(self.frame_indices)[idx], series=dict(self.series),
                       extra=dict(self.extra))

    def last_frame(self) -> Trajectory:
        """A copy keeping the last particle frame only and every time series whole (small to store)."""
        return self.select_frames([self.n_frames - 1]) if self.n_frames else self.select_frames([])

    # -- time series -----------------------------------------------------------------------------
    def add_series(self, name: str, times: np.ndarray, values: np.ndarray, unit: str = "",
                   description: str = "") -> TimeSeries:
        """Add (or replace) the series ``name``; returns it."""
        s = TimeSeries(times=times, values=values, unit=unit, description=description)
        self.series[name] = s
        return s


#: the default frame cap of :meth:`Simulator.render <invphys.core.interfaces.Simulator.render>`
DEFAULT_MAX_FRAMES = 60


def frame_selection(n_frames: int, max_frames: int) -> np.ndarray:
    """Indices of at most ``max_frames`` of ``n_frames`` frames, evenly spread, always ending on the last.

    ``max_frames = 1`` gives the last frame only (the final state); renderers use this as their cap.
    """
    if n_frames <= 0 or max_frames <= 0:
        return np.zeros(0, dtype=np.int64)
    if n_frames <= max_frames:
        return np.arange(n_frames, dtype=np.int64)
    if max_frames == 1:
        return np.array([n_frames - 1], dtype=np.int64)
    return np.unique(np.round(np.linspace(0, n_frames - 1, max_frames)).astype(np.int64))


@dataclass
class Rendering:
    """The files a :meth:`Simulator.render <invphys.core.interfaces.Simulator.render>` call wrote.

    Attributes:
        images: PNG images, in display order (frames first; at most the ``max_frames`` asked for,
            plus at most one summary image such as a plot of the time series).
        animation: the GIF/MP4 animation, or None (one frame, or ``animation="none"``).
        files: any other files written (e.g. ``.ply`` point clouds for ParaView).
    """

    images: list[Path] = field(default_factory=list)
    animation: Path | None = None
    files: list[Path] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"images": [str(p) for p in self.images], "files": [str(p) for p in self.files],
                "animation": None if self.animation is None else str(self.animation)}


@dataclass
class RunStats:
    """Provenance and cost of one simulation run (stored with every dataset row).

    Attributes:
        substeps: integration steps the run took (0 if the simulator has no such notion).
        wall_time_s: wall-clock seconds spent on this run (a batch's time divided by its size).
        backend: the compute backend that ran it; equal to the simulator config's ``backend`` field
            when it has one (e.g. ``"taichi"``), else a fixed name such as ``"numpy"``.
        device: where it ran (``"cpu"``, ``"cuda:0"``); provenance only, not identity.
        preset: the named resolution/fidelity preset (the config's ``preset`` field), or ``""``.
        simulator: the simulator's plugin ``name``.
        simulator_version: the simulator's ``version`` class attribute at run time.
    """

    substeps: int = 0
    wall_time_s: float = 0.0
    backend: str = ""
    device: str = ""
    preset: str = ""
    simulator: str = ""
    simulator_version: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class SimulationResult:
    """The outcome of simulating one parameter vector.

    Attributes:
        params: (d,) physical parameters of this run, as passed in.
        ok: False when the run failed (blew up, left the domain, exceeded its step budget).
        stats: provenance and cost (filled for failed runs too).
        failure: for a failed run, a short reason starting with a category and a colon (e.g.
            ``"nan: non-finite particle velocity at frame 37"``); None when ``ok``.
        trajectory: the recorded :class:`Trajectory` of an ok run (None for failed runs, and after an
            executor has extracted features).
        features: (M,) features when an executor streamed the trajectory to a feature extractor.
    """

    params: np.ndarray
    ok: bool
    stats: RunStats
    failure: str | None = None
    trajectory: Trajectory | None = None
    features: np.ndarray | None = None


@dataclass
class OptimizationResult:
    """What an optimiser returns for one target or objective.

    Attributes:
        theta: best normalised parameters in [0, 1]^d (decoded when the search ran in a latent space).
        point: the best point in the optimiser's own search space (theta itself in the raw space).
        score: the objective value of ``theta`` (higher is better; R_gt for recovery).
        evaluations: the number of surrogate evaluations spent.
        history: best-so-far score after each evaluation batch, as (evaluations, score) pairs.
        wall_time_s: time spent in ``optimize``.
        info: optimiser-specific details (e.g. the CMA-ES stop reason).
    """

    theta: np.ndarray
    point: np.ndarray
    score: float
    evaluations: int
    history: list[tuple[int, float]] = field(default_factory=list)
    wall_time_s: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class ValidationRecord:
    """One theta* re-run through the real simulator (the paper's validation protocol).

    ``gap`` is ``r_surrogate - r_actual``: large positive gaps mean the optimiser exploited the
    surrogate. ``r_actual`` is NaN and ``failure`` set when the validation run itself failed.
    """

    theta: np.ndarray
    target: np.ndarray
    predicted: np.ndarray
    actual: np.ndarray | None
    r_surrogate: float
    r_actual: float
    gap: float
    failure: str | None = None
    stats: RunStats | None = None
