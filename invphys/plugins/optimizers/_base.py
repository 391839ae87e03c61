"""Shared machinery of the built-in optimisers: budget-exact evaluation with best-so-far tracking."""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.interfaces import Optimizer, Problem
from invphys.core.results import OptimizationResult


class BudgetExhausted(Exception):
    """Raised inside an optimiser loop when the problem's budget is spent."""


class Tracker:
    """Evaluates batches of search points for a :class:`Problem`, never past its budget.

    Keeps the best point, its features, its score and a best-so-far history of
    ``(evaluations, score)`` pairs (one per batch).
    """

    def __init__(self, problem: Problem, budget: int | None = None) -> None:
        self.problem = problem
        self.budget = int(problem.budget if budget is None else min(budget, problem.budget))
        self.evaluations = 0
        self.best_point: np.ndarray | None = None
        self.best_features: np.ndarray | None = None
        self.best_score = -np.inf
        self.history: list[tuple[int, float]] = []
        self.start = time.perf_counter()

    @property
    def remaining(self) -> int:
        return self.budget - self.evaluations

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Scores (B',) of the first ``B' = min(B, remaining)`` rows of ``points`` (clipped to the space).

        Raises :class:`BudgetExhausted` when nothing remains.
        """
        pts = self.problem.space.clip(np.atleast_2d(np.asarray(points, dtype=np.float64)))
        if self.remaining <= 0:
            raise BudgetExhausted
        pts = pts[: self.remaining]
        y = np.atleast_2d(np.asarray(self.problem.predict(pts), dtype=np.float64))
        scores = np.asarray(self.problem.objective(y), dtype=np.float64).reshape(-1)
        scores = np.where(np.isfinite(scores), scores, -np.inf)
        self.record(pts, y, scores)
        return scores

    def record(self, points: np.ndarray, y: np.ndarray, scores: np.ndarray) -> None:
        """Account for evaluations made elsewhere (e.g. inside an RL environment)."""
        self.evaluations += len(points)
        if len(scores):
            i = int(np.argmax(scores))
            if self.best_point is None or scores[i] > self.best_score:
                self.best_score = float(scores[i])
                self.best_point = np.array(points[i], dtype=np.float64)
                self.best_features = np.array(y[i], dtype=np.float64)
        self.history.append((self.evaluations, float(self.best_score)))

    def result(self, **info: Any) -> OptimizationResult:
        if self.best_point is None:
            raise InvphysError("the optimiser evaluated no point (budget 0?)")
        theta = np.asarray(self.problem.space.to_theta(self.best_point[None, :]), dtype=np.float64)[0]
        info = {"predicted": self.best_features.tolist() if self.best_features is not None else None, **info}
        return OptimizationResult(theta=theta, point=self.best_point, score=self.best_score,
                                  evaluations=self.evaluations, history=self.history,
                                  wall_time_s=time.perf_counter() - self.start, info=info)


class BuiltinOptimizer(Optimizer):
    """Base of the built-in optimisers: exposes the evaluation budget the runner should allow.

    ``problems`` tells the invert stage what to run the optimiser on: ``"both"`` (held-out targets and
    named objectives), ``"targets"`` or ``"objectives"``.
    """

    problems: ClassVar[str] = "both"

    @property
    def evaluation_budget(self) -> int:
        """Evaluations one :meth:`optimize` call spends with this configuration."""
        return int(getattr(self.config, "budget", 0))


class AskTell:
    """The ask/tell interface: the caller evaluates the points however it likes (a surrogate, or the
    real simulator in one batch) and reports the scores back.

    ``ask()`` returns the next points (B, dim) in the search space (empty when finished); ``tell(points,
    scores)`` reports their scores (higher is better); ``best_point``/``best_score`` and ``told`` (points
    told so far) track the search. A subclass implements :meth:`_ask` and :meth:`_tell`.
    """

    def __init__(self) -> None:
        self.best_point: np.ndarray | None = None
        self.best_score = -np.inf
        self.told = 0
        self.history: list[tuple[int, float]] = []

    @property
    def done(self) -> bool:
        return False

    def ask(self) -> np.ndarray:
        return np.empty((0, 0)) if self.done else self._ask()

    def tell(self, points: np.ndarray, scores: np.ndarray) -> None:
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        scores = np.asarray(scores, dtype=np.float64).reshape(-1)
        scores = np.where(np.isfinite(scores), scores, -np.inf)
        if len(points) != len(scores):
            raise InvphysError(f"tell: {len(points)} points and {len(scores)} scores")
        self.told += len(points)
        if len(scores):
            i = int(np.argmax(scores))
            if self.best_point is None or scores[i] > self.best_score:
                self.best_score, self.best_point = float(scores[i]), points[i].copy()
        self.history.append((self.told, float(self.best_score)))
        self._tell(points, scores)

    def _ask(self) -> np.ndarray:
        raise NotImplementedError

    def _tell(self, points: np.ndarray, scores: np.ndarray) -> None:
        raise NotImplementedError
