"""R_gt over the features a target gives (partial targets leave the others out of R): the score every inverter
answer, baseline and diagnosis ranks by, below them all in core."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from invphys.core.objectives import Objective


def masked_recovery(y: np.ndarray, target: np.ndarray, scales: np.ndarray, mask: np.ndarray | None = None,
                    kappa: float = 3.0) -> np.ndarray:
    """``exp(-kappa * sqrt(mean over given k of ((y_k - y*_k) / s_k)^2))``; equals the paper's eq. 1
    when every feature is given. Shapes broadcast like :func:`~invphys.core.objectives.recovery_reward`."""
    y = np.asarray(y, dtype=np.float64)
    t = np.asarray(target, dtype=np.float64)
    if mask is None:
        z = (y - t) / scales
        ms = np.mean(z * z, axis=-1)
    else:
        w = np.broadcast_to(np.asarray(mask, dtype=np.float64), np.broadcast_shapes(y.shape, t.shape))
        z = (y - np.where(w > 0, t, 0.0)) / scales
        ms = np.sum(np.where(w > 0, z * z, 0.0), axis=-1) / np.maximum(w.sum(axis=-1), 1.0)
    r = np.exp(-kappa * np.sqrt(ms))
    return np.where(np.isfinite(r), r, 0.0)


@dataclass
class MaskedRecovery(Objective):
    """R_gt against one target, over its given features."""

    target: np.ndarray
    scales: np.ndarray
    mask: np.ndarray | None = None
    kappa: float = 3.0
    name: str = "recovery"

    def __call__(self, features: np.ndarray) -> np.ndarray:
        return masked_recovery(features, self.target, self.scales, self.mask, self.kappa)
