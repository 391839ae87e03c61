"""What a dataset baseline is: fitted on training rows, answers many targets at once."""

from __future__ import annotations

import time
from abc import abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.interfaces import Problem
from invphys.core.results import OptimizationResult
from invphys.plugins.optimizers._base import BuiltinOptimizer

#: std of U(0, 1): a parameter's spread before seeing any data (normalised space)
PRIOR_STD = float(np.sqrt(1.0 / 12.0))


@dataclass
class BaselineAnswers:
    """A baseline's answers for B targets.

    ``theta`` (B, d) are the answers in [0, 1]^d; ``candidates`` (B, K, d) the candidates each answer
    was chosen from (K = 1 when there is no choice); ``spread`` (B, d) each parameter's spread over the
    candidates or the posterior, in units of the prior's std (about 1: the data did not pin it down);
    ``evaluations`` (B,) surrogate evaluations spent per target; ``wall_time_s`` for the whole batch.
    """

    theta: np.ndarray
    candidates: np.ndarray
    spread: np.ndarray
    evaluations: np.ndarray
    wall_time_s: float
    info: dict[str, Any] = field(default_factory=dict)


def learns_from_rows(plugin: Any) -> bool:
    """True for an optimiser (class or instance) answered from training rows: it has
    ``fit(theta, y, scales)`` (every :class:`DatasetBaseline`, and third-party ones shaped alike)."""
    import inspect

    fit = getattr(plugin, "fit", None)
    return fit is not None and {"theta", "y", "scales"} <= set(inspect.signature(fit).parameters)


def answer_with_penalty(plugin: Any, targets: np.ndarray, predict_theta: Any, surrogate: Any, scales: np.ndarray,
                        where: str) -> BaselineAnswers:
    """``plugin.answer(targets, predict_theta)``; where the plugin's config sets ``uncertainty_penalty`` > 0,
    its candidates are chosen by R minus lambda x ``surrogate``'s normalised std instead (an ensemble's
    ``predict_with_uncertainty``). ``where`` names the plugin's block in errors."""
    lam = float(getattr(plugin.config, "uncertainty_penalty", 0.0) or 0.0)
    if lam <= 0:
        return plugin.answer(targets, predict_theta)
    if surrogate is None or not hasattr(surrogate, "predict_with_uncertainty"):
        raise InvphysError(f"{where}.uncertainty_penalty needs a surrogate with uncertainty (the ensemble)")
    from invphys.evaluators.uncertainty import UncertaintyPenalty

    pen = UncertaintyPenalty(surrogate, scales, lam)
    return plugin.answer(targets, pen.predict, pen.penalty)


class DatasetBaseline(BuiltinOptimizer):
    """An optimiser plugin answered from the training rows rather than by search.

    Call :meth:`fit` with the training rows first; then :meth:`answer` takes a batch of targets (what
    the evaluation uses) and :meth:`optimize` one :class:`Problem` (the optimiser interface; its
    ``target`` must be set, and a search space other than raw gets the answer through
    ``space.from_theta``). ``predict_theta`` (normalised parameters -> features, e.g. the shared
    surrogate) is only needed by options that choose among candidates with the surrogate.
    """

    goal_conditioned: ClassVar[bool] = True
    problems: ClassVar[str] = "targets"
    #: extras the plugin needs (named in the error when missing)
    extra: ClassVar[str] = ""

    def __init__(self, config: Any = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self.penalty_fn: Any = None  # set by answer() for the candidates' choice
        self.fitted = False
        self.metrics: dict[str, Any] = {}

    @property
    def prepared(self) -> bool:
        return self.fitted

    @property
    def evaluation_budget(self) -> int:
        return int(getattr(self.config, "candidates", 0) or 0) or 1

    def prepare(self, space: Any, predict: Any, train_targets: np.ndarray, scales: np.ndarray,
                progress: bool = False) -> dict[str, Any]:
        if not self.fitted:
            raise InvphysError(f"{self.name} is a dataset baseline: it needs the training rows (parameters and "
                               f"features); list it under evaluation.baselines, or call fit(theta, y, scales)")
        return self.metrics

    def fit(self, theta: np.ndarray, y: np.ndarray, scales: np.ndarray, progress: bool = False) -> dict[str, Any]:
        """Learn from training rows: ``theta`` (N, d) in [0, 1]^d, features ``y`` (N, M), scales s_k (M,)."""
        theta = np.asarray(theta, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if theta.ndim != 2 or y.ndim != 2 or len(theta) != len(y) or len(theta) < 2:
            raise InvphysError(f"{self.name}: needs (N >= 2, d) parameters and (N, M) features, got "
                               f"{theta.shape} and {y.shape}")
        keep = np.all(np.isfinite(y), axis=1) & np.all(np.isfinite(theta), axis=1)
        t0 = time.perf_counter()
        self.metrics = {**self._fit(theta[keep], y[keep], np.asarray(scales, dtype=np.float64), progress),
                        "train_rows": int(keep.sum()), "fit_time_s": time.perf_counter() - t0}
        self.fitted = True
        return self.metrics

    def answer(self, targets: np.ndarray, predict_theta: Any = None, penalty: Any = None) -> BaselineAnswers:
        """Answers for targets (B, M) (see :class:`BaselineAnswers`).

        ``penalty(features (N, M)) -> (N,)`` is subtracted from R_gt where an option chooses among
        candidates by the surrogate (e.g. :meth:`UncertaintyPenalty.penalty
        <invphys.evaluators.uncertainty.UncertaintyPenalty.penalty>` with ``predict_theta`` its
        ``predict``).
        """
        if not self.fitted:
            raise InvphysError(f"{self.name}: call fit() with training rows before answering")
        targets = np.atleast_2d(np.asarray(targets, dtype=np.float64))
        t0 = time.perf_counter()
        self.penalty_fn = penalty
        try:
            ans = self._answer(targets, predict_theta)
        finally:
            self.penalty_fn = None
        ans.wall_time_s = time.perf_counter() - t0
        return ans

    def optimize(self, problem: Problem) -> OptimizationResult:
        if problem.target is None:
            raise InvphysError(f"{self.name} answers recovery problems only (the problem has no target)")
        counted = problem.info.get("theta_predict")
        unc = problem.info.get("uncertainty")  # a penalised problem (optimizers.<label>.uncertainty_penalty)
        ans = self.answer(problem.target[None, :], counted, None if unc is None else unc.penalty)
        theta = ans.theta[0]
        space = problem.space
        point = theta if space.from_theta is None else np.asarray(space.from_theta(theta[None, :]))[0]
        y = np.asarray(problem.predict(space.clip(point[None, :])))
        score = float(np.asarray(problem.objective(y)).reshape(-1)[0])
        evals = int(ans.evaluations[0]) + 1
        return OptimizationResult(theta=theta, point=point, score=score, evaluations=evals,
                                  history=[(evals, score)], wall_time_s=ans.wall_time_s,
                                  info={"predicted": y[0].tolist(), "spread": ans.spread[0].tolist()})

    @abstractmethod
    def _fit(self, theta: np.ndarray, y: np.ndarray, scales: np.ndarray, progress: bool) -> dict[str, Any]:
        """Fit on finite training rows; return metrics."""

    @abstractmethod
    def _answer(self, targets: np.ndarray, predict_theta: Any) -> BaselineAnswers:
        """Answers (wall time is filled in by :meth:`answer`)."""


def best_by_surrogate(candidates: np.ndarray, targets: np.ndarray, scales: np.ndarray,
                      predict_theta: Any, penalty: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Index (B,) of the candidate (B, K, d) whose surrogate prediction scores best, and the scores (B, K).

    The score is R_gt, minus ``penalty(features (B*K, M)) -> (B*K,)`` when given.
    """
    from invphys.core.objectives import recovery_reward

    if predict_theta is None:
        raise InvphysError("choosing among candidates by the surrogate needs a surrogate (predict_theta)")
    b, k, d = candidates.shape
    flat = np.asarray(predict_theta(candidates.reshape(b * k, d)), dtype=np.float64)
    scores = recovery_reward(flat.reshape(b, k, -1), targets[:, None, :], scales)
    if penalty is not None:
        scores = scores - np.asarray(penalty(flat), dtype=np.float64).reshape(b, k)
    return np.argmax(scores, axis=1), scores
