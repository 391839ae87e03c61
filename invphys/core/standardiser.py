"""The project's one feature standardiser: z-scores ``(y - mean) / std`` per column.

Every place that standardises features uses it: target selection (farthest-point sampling), the
observation of the RL environments, the PPO optimisers, and the networks of the learned models
(which keep its ``mean``/``std`` as buffers, so that a saved state dict is the whole model).

A column without spread (``std <= rtol * max(1, |mean|)``, e.g. a damage that is always 0) gets
``std = max(1, |mean|)``: it is centred, never blown up, the same rule as
:func:`~invphys.core.objectives.percentile_scales`. NaNs are ignored when fitting.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Standardiser:
    """Per-column ``mean`` and ``std`` (both (M,)); unpacks as ``mean, std = standardiser``."""

    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, y: np.ndarray, rtol: float = 1e-9) -> Standardiser:
        """Column statistics of ``y`` (N, M) (NaN-aware), constant columns centred only."""
        arr = np.asarray(y, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[0] == 0:
            raise ValueError(f"a standardiser is fitted on a non-empty (N, M) array, got shape {arr.shape}")
        mean, std = np.nanmean(arr, axis=0), np.nanstd(arr, axis=0)
        fallback = np.maximum(1.0, np.abs(mean))
        return cls(mean=mean, std=np.where(std > rtol * fallback, std, fallback))

    def transform(self, y: np.ndarray) -> np.ndarray:
        """z-scores of ``y`` (..., M)."""
        return (np.asarray(y, dtype=np.float64) - self.mean) / self.std

    def inverse(self, z: np.ndarray) -> np.ndarray:
        """Features (..., M) of z-scores."""
        return np.asarray(z, dtype=np.float64) * self.std + self.mean

    def __iter__(self) -> Iterator[np.ndarray]:
        yield self.mean
        yield self.std
