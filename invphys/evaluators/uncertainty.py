"""An uncertainty-penalised evaluator: score = R - lambda * normalised ensemble std.

The normalised std of a prediction is ``sqrt(mean_k (std_k / s_k)^2)``, the ensemble members'
disagreement on the same per-feature scales s_k that R_gt uses. A surrogate without uncertainty
(``predict_with_uncertainty`` returning zeros) makes the penalty 0.

Use it with an optimiser through :func:`penalised_problem`, or with an RL environment
(:class:`~invphys.envs.task.InverseTask`) through :meth:`UncertaintyPenalty.predict` and
:meth:`UncertaintyPenalty.score_fn`::

    pen = UncertaintyPenalty(ensemble, scales, lam=0.5)
    task = InverseTask(..., predict=pen.predict_points(space.to_theta), score=pen.score_fn(base_score))
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from invphys.core.interfaces import Problem


def normalised_std(std: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """(B,) RMS over features of ``std / scales`` for ``std`` (B, M)."""
    z = np.asarray(std, dtype=np.float64) / np.maximum(np.asarray(scales, dtype=np.float64), 1e-12)
    return np.sqrt(np.mean(z * z, axis=-1))


class UncertaintyPenalty:
    """Predicts with a surrogate's (mean, std) and remembers each prediction's normalised std.

    :meth:`predict` returns the mean features (so every consumer sees ordinary features) and keeps
    the std of each returned row, keyed by the row's bytes; :meth:`penalty` looks it up again for the
    features an objective is handed. Rows it never predicted get no penalty.
    """

    def __init__(self, surrogate: Any, scales: np.ndarray, lam: float, max_cache: int = 200_000) -> None:
        self.surrogate = surrogate
        self.scales = np.asarray(scales, dtype=np.float64)
        self.lam = float(lam)
        self.max_cache = int(max_cache)
        self._u: dict[bytes, float] = {}

    def predict(self, theta: np.ndarray) -> np.ndarray:
        """Mean features (B, M) of normalised parameters (B, d); their normalised std is remembered."""
        mean, std = self.surrogate.predict_with_uncertainty(np.atleast_2d(np.asarray(theta, dtype=np.float64)))
        mean = np.ascontiguousarray(mean, dtype=np.float64)
        if len(self._u) > self.max_cache:
            self._u.clear()
        for row, u in zip(mean, normalised_std(std, self.scales), strict=True):
            self._u[row.tobytes()] = float(u)
        return mean

    def predict_points(self, to_theta: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
        """A predictor over search points (decoded with ``to_theta``)."""
        return lambda points: self.predict(to_theta(points))

    def uncertainty(self, features: np.ndarray) -> np.ndarray:
        """(B,) normalised std remembered for each row of ``features`` (0 when unknown)."""
        y = np.ascontiguousarray(np.atleast_2d(features), dtype=np.float64)
        return np.array([self._u.get(row.tobytes(), 0.0) for row in y])

    def penalty(self, features: np.ndarray) -> np.ndarray:
        """(B,) lambda * normalised std of each row."""
        return self.lam * self.uncertainty(features)

    def objective(self, base: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
        """``base(features) - penalty(features)``."""
        def penalised(features: np.ndarray) -> np.ndarray:
            return np.asarray(base(features), dtype=np.float64) - self.penalty(features)
        return penalised

    def score_fn(self, base: Callable[[np.ndarray, np.ndarray | None], np.ndarray]
                 ) -> Callable[[np.ndarray, np.ndarray | None], np.ndarray]:
        """For :class:`~invphys.envs.task.InverseTask`: ``base(features, goals) - penalty(features)``."""
        def penalised(features: np.ndarray, goals: np.ndarray | None) -> np.ndarray:
            return np.asarray(base(features, goals), dtype=np.float64) - self.penalty(features)
        return penalised


def penalised_problem(problem: Problem, surrogate: Any, scales: np.ndarray, lam: float) -> Problem:
    """A copy of ``problem`` scored on ``surrogate`` with the uncertainty penalty (same budget, counted).

    The copy's ``info["counter"]`` counts its evaluations; ``info["uncertainty"]`` is the
    :class:`UncertaintyPenalty` (its :meth:`~UncertaintyPenalty.uncertainty` gives each answer's std).
    """
    from invphys.core.spaces import EvaluationCounter

    pen = UncertaintyPenalty(surrogate, scales, lam)
    counter = EvaluationCounter(pen.predict_points(problem.space.to_theta))
    info = {**problem.info, "counter": counter, "uncertainty": pen, "theta_predict": counter.wrap(pen.predict)}
    return Problem(space=problem.space, predict=counter, objective=pen.objective(problem.objective),
                   budget=problem.budget, target=problem.target, initial=problem.initial, seed=problem.seed,
                   info=info)
