"""Plain data passed between pipeline stages: trajectories, simulation results, optimisation results.

These are light dataclasses over NumPy arrays, so that every stage can be tested and stored without
importing a simulator backend or torch.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np


@dataclass
class Trajectory:
    """Recorded frames of one particle simulation.

    Attributes:
        positions: (T, N, 3) float32 particle positions at the recorded frames.
        damage: (T, N) float32 damage in [0, 1] (0 = intact) at the recorded frames.
        labels: (N,) int8 region label of every particle (meaning defined by the simulator,
            e.g. 0 = skin, 1 = interior for the orange peel).
        frame_indices: (T,) int indices of the recorded frames in the full frame sequence.
        fps: frames per second of the full frame sequence (time of frame k is k / fps).
        extra: simulator-specific arrays or scalars (e.g. the gripper path).
    """

    positions: np.ndarray
    damage: np.ndarray
    labels: np.ndarray
    frame_indices: np.ndarray
    fps: float
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_particles(self) -> int:
        return int(self.positions.shape[1])

    def times(self) -> np.ndarray:
        """Simulated time in seconds of each recorded frame."""
        return np.asarray(self.frame_indices, dtype=np.float64) / self.fps


@dataclass
class RunStats:
    """Provenance and cost of one simulation run."""

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

    ``ok`` is False when the run blew up; then ``failure`` names the reason (e.g.
    ``"nan: non-finite particle velocity at frame 37"``) and ``trajectory``/``features`` are None.
    ``features`` is filled when the executor streams frames to a feature extractor instead of keeping
    the trajectory.
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
