"""Objectives over behavioural features: the paper's recovery reward R_gt and weighted objectives.

All objectives are vectorised: they take features of shape (B, M) (or (M,)) and return scores of
shape (B,) (or a float), higher being better.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from invphys.core.standardiser import Standardiser


def percentile_scales(features: np.ndarray, low: float = 5.0, high: float = 95.0,
                      rtol: float = 1e-9) -> np.ndarray:
    """Per-feature scale ``s_k = p_high - p_low`` over a dataset (paper: p95 - p5).

    A feature without spread in the data (``s_k <= rtol * max(1, |median_k|)``, e.g. a damage that is
    always 0) carries no information about the parameters; it gets the scale ``max(1, |median_k|)``
    instead, so that a surrogate's tiny deviation on it cannot drive R_gt to 0.
    """
    y = np.asarray(features, dtype=np.float64)
    if y.ndim != 2 or y.shape[0] < 2:
        raise ValueError(f"percentile_scales needs a (N >= 2, M) array, got shape {y.shape}")
    s = np.nanpercentile(y, high, axis=0) - np.nanpercentile(y, low, axis=0)
    fallback = np.maximum(1.0, np.abs(np.nanmedian(y, axis=0)))
    return np.where(s > rtol * fallback, s, fallback)


def feature_standardiser(features: np.ndarray, rtol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) per feature for z-scores: :meth:`Standardiser.fit <invphys.core.standardiser.Standardiser.fit>`."""
    mean, std = Standardiser.fit(features, rtol)
    return mean, std


def recovery_reward(y: np.ndarray, target: np.ndarray, scales: np.ndarray, kappa: float = 3.0) -> np.ndarray:
    """The paper's eq. 1: ``R_gt = exp(-kappa * sqrt(mean_k ((y_k - y*_k) / s_k)^2))``.

    ``y`` may be (M,) or (B, M); ``target`` (M,) or broadcastable to ``y``. Returns (B,) or a 0-d
    array. Non-finite predictions score 0.
    """
    y = np.asarray(y, dtype=np.float64)
    z = (y - np.asarray(target, dtype=np.float64)) / np.asarray(scales, dtype=np.float64)
    rms = np.sqrt(np.mean(z * z, axis=-1))
    r = np.exp(-kappa * rms)
    return np.where(np.isfinite(r), r, 0.0)


class Objective(ABC):
    """A score over features, higher is better. Subclass and implement :meth:`__call__`."""

    name: str = "objective"

    @abstractmethod
    def __call__(self, features: np.ndarray) -> np.ndarray:
        """Scores (B,) for features (B, M)."""


@dataclass
class RecoveryObjective(Objective):
    """R_gt against a fixed target y* (the inverse-recovery objective)."""

    target: np.ndarray
    scales: np.ndarray
    kappa: float = 3.0
    name: str = "recovery"

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return recovery_reward(features, self.target, self.scales, self.kappa)


@dataclass
class WeightedObjective(Objective):
    """A weighted sum of percentile-normalised feature terms (the paper's "firm"/"ripe" peel).

    Each feature is mapped to ``(y_k - p5_k) / (p95_k - p5_k)`` (so roughly [0, 1] over the dataset),
    clipped to ``[-clip, 1 + clip]``, and the score is ``sum_k w_k * term_k / sum_k |w_k|``. A positive
    weight rewards a high feature value, a negative weight a low one.
    """

    weights: np.ndarray
    p5: np.ndarray
    p95: np.ndarray
    clip: float = 0.5
    name: str = "weighted"

    def __call__(self, features: np.ndarray) -> np.ndarray:
        y = np.asarray(features, dtype=np.float64)
        span = np.maximum(self.p95 - self.p5, 1e-12)
        terms = np.clip((y - self.p5) / span, -self.clip, 1.0 + self.clip)
        w = np.asarray(self.weights, dtype=np.float64)
        score = terms @ w / max(float(np.abs(w).sum()), 1e-12)
        return np.where(np.isfinite(score), score, -np.inf)

    @classmethod
    def from_names(cls, weights: Mapping[str, float], feature_names: Sequence[str],
                   dataset_features: np.ndarray, name: str = "weighted") -> WeightedObjective:
        """Build from ``{feature_name: weight}`` and a dataset's features (for the percentiles)."""
        unknown = sorted(set(weights) - set(feature_names))
        if unknown:
            from invphys.core.errors import InvphysError, did_you_mean

            raise InvphysError(
                "unknown feature(s) in objective weights: "
                + "; ".join(f"{u!r}{did_you_mean(u, feature_names)}" for u in unknown)
            )
        w = np.array([float(weights.get(n, 0.0)) for n in feature_names])
        y = np.asarray(dataset_features, dtype=np.float64)
        return cls(weights=w, p5=np.nanpercentile(y, 5, axis=0), p95=np.nanpercentile(y, 95, axis=0),
                   name=name)
