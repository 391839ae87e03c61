"""The inverse-design episode logic, vectorised over a batch of episodes (NumPy only)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.standardiser import Standardiser

#: scores (B,) of features (B, M) against per-episode goals (B, M) (None when not goal-conditioned)
ScoreFn = Callable[[np.ndarray, np.ndarray | None], np.ndarray]
#: goals (n, M) in feature units drawn with a generator
GoalSampler = Callable[[np.random.Generator, int], np.ndarray]
#: bound of the observation's standardised features and score (non-finite values are mapped to it)
OBS_LIMIT = 1e6


@dataclass
class InverseTask:
    """One inverse-design task: a box, a feature predictor, a score, and the episode rules.

    Observation (float32): ``[s, y_hat, (y*,) R, t/T]`` with ``y_hat`` and ``y*`` standardised by
    ``feature_mean``/``feature_std``; ``y*`` only when ``goal_sampler`` is set (goal-conditioned).
    Every episode starts at ``start`` (default the box centre) whose features are predicted once and
    cached, so an episode of T steps costs exactly T surrogate evaluations. The reward is sparse:
    0 before step T and, at step T, the best score among the T visited states.
    """

    low: float
    high: float
    dim: int
    predict: Callable[[np.ndarray], np.ndarray]
    score: ScoreFn
    feature_mean: np.ndarray
    feature_std: np.ndarray
    horizon: int = 8
    step_scale: float = 0.5
    start: np.ndarray | None = None
    goal_sampler: GoalSampler | None = None
    on_evaluate: Callable[[np.ndarray, np.ndarray, np.ndarray], None] | None = None
    start_features: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        if self.horizon < 1:
            raise InvphysError(f"horizon T must be >= 1, got {self.horizon}")
        self.feature_mean = np.asarray(self.feature_mean, dtype=np.float64).reshape(-1)
        self.feature_std = np.maximum(np.asarray(self.feature_std, dtype=np.float64).reshape(-1), 1e-12)
        if self.start is None:
            self.start = np.full(self.dim, 0.5 * (self.low + self.high))
        self.start = np.clip(np.asarray(self.start, dtype=np.float64).reshape(self.dim), self.low, self.high)
        if self.start_features is None:
            self.start_features = np.asarray(self.predict(self.start[None, :]), dtype=np.float64)[0]
        self.start_features = np.asarray(self.start_features, dtype=np.float64).reshape(-1)

    @property
    def n_features(self) -> int:
        return int(self.feature_mean.shape[0])

    @property
    def goal_conditioned(self) -> bool:
        return self.goal_sampler is not None

    @property
    def obs_dim(self) -> int:
        return self.dim + self.n_features * (2 if self.goal_conditioned else 1) + 2

    def obs_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower/upper observation bounds (standardised features and the score within +-OBS_LIMIT)."""
        m = self.n_features * (2 if self.goal_conditioned else 1)
        low = np.concatenate([np.full(self.dim, self.low), np.full(m + 1, -OBS_LIMIT), [0.0]])
        high = np.concatenate([np.full(self.dim, self.high), np.full(m + 1, OBS_LIMIT), [1.0]])
        return low.astype(np.float32), high.astype(np.float32)

    @property
    def standardiser(self) -> Standardiser:
        """The observation's feature standardiser (``feature_mean``, ``feature_std``)."""
        return Standardiser(self.feature_mean, self.feature_std)

    def standardise(self, y: np.ndarray) -> np.ndarray:
        return self.standardiser.transform(y)

    def observe(self, s: np.ndarray, y: np.ndarray, goals: np.ndarray | None, r: np.ndarray,
                t: np.ndarray) -> np.ndarray:
        parts = [s, self.standardise(y)]
        if self.goal_conditioned:
            if goals is None:
                raise InvphysError("a goal-conditioned task needs goals")
            parts.append(self.standardise(goals))
        parts += [np.asarray(r, dtype=np.float64).reshape(-1, 1),
                  (np.asarray(t, dtype=np.float64) / self.horizon).reshape(-1, 1)]
        obs = np.nan_to_num(np.concatenate(parts, axis=1), nan=0.0, posinf=OBS_LIMIT, neginf=-OBS_LIMIT)
        return np.clip(obs, -OBS_LIMIT, OBS_LIMIT).astype(np.float32)


class EpisodeBatch:
    """The state of ``n`` parallel episodes of an :class:`InverseTask`."""

    def __init__(self, task: InverseTask, n: int, rng: np.random.Generator) -> None:
        self.task = task
        self.n = n
        self.rng = rng
        m = task.n_features
        self.s = np.zeros((n, task.dim))
        self.y = np.zeros((n, m))
        self.goals: np.ndarray | None = np.zeros((n, m)) if task.goal_conditioned else None
        self.r = np.zeros(n)
        self.best = np.full(n, -np.inf)
        self.t = np.zeros(n, dtype=np.int64)

    def reset(self, rows: np.ndarray | None = None, goals: np.ndarray | None = None) -> None:
        """Restart ``rows`` (default all) at the task's start; draw goals unless ``goals`` is given."""
        task = self.task
        rows = np.arange(self.n) if rows is None else np.asarray(rows, dtype=np.int64)
        if len(rows) == 0:
            return
        self.s[rows] = task.start
        self.y[rows] = task.start_features
        if self.goals is not None:
            if goals is None:
                assert task.goal_sampler is not None
                goals = task.goal_sampler(self.rng, len(rows))
            self.goals[rows] = np.broadcast_to(np.asarray(goals, dtype=np.float64), (len(rows), task.n_features))
        g = None if self.goals is None else self.goals[rows]
        self.r[rows] = np.asarray(task.score(self.y[rows], g), dtype=np.float64).reshape(-1)
        self.best[rows] = -np.inf
        self.t[rows] = 0

    def observe(self) -> np.ndarray:
        return self.task.observe(self.s, self.y, self.goals, self.r, self.t)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Advance all episodes with ONE predict call; return (rewards (n,), done (n,))."""
        task = self.task
        a = np.clip(np.asarray(actions, dtype=np.float64).reshape(self.n, task.dim), -1.0, 1.0)
        self.s = np.clip(self.s + task.step_scale * a, task.low, task.high)
        self.y = np.asarray(task.predict(self.s), dtype=np.float64).reshape(self.n, task.n_features)
        r = np.asarray(task.score(self.y, self.goals), dtype=np.float64).reshape(-1)
        self.r = np.where(np.isfinite(r), r, 0.0)
        if task.on_evaluate is not None:
            task.on_evaluate(self.s.copy(), self.y.copy(), self.r.copy())
        self.best = np.maximum(self.best, self.r)
        self.t += 1
        done = self.t >= task.horizon
        rewards = np.where(done, self.best, 0.0)
        return rewards.astype(np.float32), done
