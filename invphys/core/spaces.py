"""Search spaces and optimisation problems: where an optimiser searches and what it is scored by.

* :func:`raw_space` is the normalised parameter box [0, 1]^d with the identity map;
* :func:`latent_space` is a latent model's box [-b, b]^k (paper: [-3, 3]^4) whose points become
  parameters through the model's decoder (clipped to [0, 1]);
* :func:`make_predict` builds the feature predictor behind a space: ``"shared"`` decodes to theta and
  evaluates the shared surrogate (the paper's decode-then-evaluate, so that every method uses one
  evaluator), ``"own_head"`` uses the latent model's own feature head (the paper's ablation);
* :func:`build_problem` wraps both with an objective and a budget into a
  :class:`~invphys.core.interfaces.Problem` whose predictor counts evaluations
  (``problem.info["counter"].count``).

Example::

    space = latent_space(flow, label="flow")
    problem = build_problem(space, surrogate=mlp, latent=flow, evaluator="shared",
                            objective=RecoveryObjective(y_star, scales), budget=5000, target=y_star)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.interfaces import Problem, SearchSpace
from invphys.core.model_protocols import FeatureHead, LatentCodec, Predictor

EVALUATORS = ("shared", "own_head")


class EvaluationCounter:
    """A predictor wrapper that counts the points it has evaluated (the optimiser's cost)."""

    def __init__(self, predict: Callable[[np.ndarray], np.ndarray]) -> None:
        self._predict = predict
        self.count = 0
        self.calls = 0

    def __call__(self, points: np.ndarray) -> np.ndarray:
        pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
        self.count += int(pts.shape[0])
        self.calls += 1
        return np.asarray(self._predict(pts), dtype=np.float64)

    def wrap(self, predict: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
        """Another predictor whose evaluations add to this counter."""

        def counted(points: np.ndarray) -> np.ndarray:
            pts = np.atleast_2d(np.asarray(points, dtype=np.float64))
            self.count += int(pts.shape[0])
            self.calls += 1
            return np.asarray(predict(pts), dtype=np.float64)

        return counted


def raw_space(dim: int, name: str = "raw") -> SearchSpace:
    """The normalised parameter box [0, 1]^dim; points are theta."""
    if dim < 1:
        raise InvphysError(f"a search space needs dim >= 1, got {dim}")

    def identity(points: np.ndarray) -> np.ndarray:
        return np.clip(np.asarray(points, dtype=np.float64), 0.0, 1.0)

    return SearchSpace(name=name, dim=int(dim), low=0.0, high=1.0, to_theta=identity, from_theta=identity)


def latent_space(model: LatentCodec, name: str = "latent", bound: float | None = None) -> SearchSpace:
    """A latent model's box [-b, b]^k (b = ``model.latent_bound`` unless given); decode clips to [0, 1]."""
    b = float(model.latent_bound if bound is None else bound)
    if b <= 0:
        raise InvphysError(f"latent bound must be > 0, got {b}")

    def decode(points: np.ndarray) -> np.ndarray:
        z = np.clip(np.atleast_2d(np.asarray(points, dtype=np.float64)), -b, b)
        return np.clip(np.asarray(model.decode(z), dtype=np.float64), 0.0, 1.0)

    def encode(theta: np.ndarray) -> np.ndarray:
        z = np.asarray(model.encode(np.atleast_2d(np.asarray(theta, dtype=np.float64))), dtype=np.float64)
        return np.clip(z, -b, b)

    return SearchSpace(name=name, dim=int(model.latent_dim), low=-b, high=b, to_theta=decode,
                       from_theta=encode)


def make_predict(space: SearchSpace, surrogate: Predictor | None, latent: FeatureHead | None = None,
                 evaluator: str = "shared") -> Callable[[np.ndarray], np.ndarray]:
    """The features (B, M) behind search points (B, dim) of ``space``.

    ``"shared"``: ``surrogate.predict(space.to_theta(points))`` (decode-then-evaluate).
    ``"own_head"``: ``latent.predict_features(points)`` (only in a latent space).
    """
    if evaluator not in EVALUATORS:
        from invphys.core.errors import did_you_mean

        raise InvphysError(f"unknown evaluator {evaluator!r}.{did_you_mean(evaluator, EVALUATORS)} "
                           f"Choose one of: {', '.join(EVALUATORS)}")
    if evaluator == "own_head":
        if latent is None:
            raise InvphysError("evaluator 'own_head' needs a latent space (the raw space has no own head); "
                               "use evaluator: shared")
        lo, hi = space.low, space.high

        def head(points: np.ndarray) -> np.ndarray:
            try:
                return np.asarray(latent.predict_features(np.clip(points, lo, hi)), dtype=np.float64)
            except NotImplementedError as exc:
                raise InvphysError(f"{exc}; use evaluator: shared") from exc

        return head
    if surrogate is None:
        raise InvphysError("evaluator 'shared' needs a trained surrogate")

    def shared(points: np.ndarray) -> np.ndarray:
        return np.asarray(surrogate.predict(space.to_theta(space.clip(points))), dtype=np.float64)

    return shared


def build_problem(space: SearchSpace, objective: Callable[[np.ndarray], np.ndarray], budget: int, *,
                  surrogate: Predictor | None = None, latent: FeatureHead | None = None,
                  evaluator: str = "shared", predict: Callable[[np.ndarray], np.ndarray] | None = None,
                  target: np.ndarray | None = None, initial: np.ndarray | None = None, seed: int = 0,
                  feature_mean: np.ndarray | None = None, feature_std: np.ndarray | None = None,
                  info: dict[str, Any] | None = None) -> Problem:
    """A :class:`Problem` over ``space`` whose predictor counts evaluations.

    ``predict`` overrides the evaluator-built predictor. ``info`` gets ``counter`` (the
    :class:`EvaluationCounter`), ``theta_predict`` (the shared surrogate over normalised parameters,
    which warm-start refinement uses), ``evaluator`` and, when given, ``feature_mean``/``feature_std``
    (feature statistics that RL observations are standardised with).
    """
    if budget < 1:
        raise InvphysError(f"an optimisation budget must be >= 1 evaluation, got {budget}")
    base = predict if predict is not None else make_predict(space, surrogate, latent, evaluator)
    counter = EvaluationCounter(base)
    extra: dict[str, Any] = {"counter": counter, "evaluator": evaluator, "space": space.name}
    if surrogate is not None:
        extra["theta_predict"] = counter.wrap(surrogate.predict)
    if feature_mean is not None:
        extra["feature_mean"] = np.asarray(feature_mean, dtype=np.float64)
    if feature_std is not None:
        extra["feature_std"] = np.maximum(np.asarray(feature_std, dtype=np.float64), 1e-12)
    extra.update(info or {})
    return Problem(space=space, predict=counter, objective=objective, budget=int(budget),
                   target=None if target is None else np.asarray(target, dtype=np.float64),
                   initial=None if initial is None else np.asarray(initial, dtype=np.float64),
                   seed=int(seed), info=extra)
