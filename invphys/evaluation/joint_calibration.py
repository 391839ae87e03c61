"""The joint step of posterior recalibration: each row's marginals moved by where the row's posterior sits.

Per-parameter quantile maps (:func:`~invphys.evaluation.calibration.fit_recalibration`) fix coverage
averaged over rows. They cannot fix a bias that changes sign across rows: a posterior shrunk towards the
middle of the box puts the truth below its median where it sits low and above where it sits high. Each
parameter's marginal coverage then averages out, but the joint check (TARP: distances to a reference
point, summed over all parameters) sees the truth farther out than the draws. On the paper bundle this
shift explained most of what TARP missed after the per-parameter maps.

The step models the truth's normal score under a row's (already mapped) marginal as
N(a0 + a1 u, b^2), with u the row's posterior median of that parameter, standardised over the rows
that fitted it; it moves the row's draws to follow that law (:func:`apply_location_shift`): ranks, hence
the dependence between parameters, are kept, and draws stay inside the box. Four plain numbers per
parameter (``center``, ``spread``, ``shift`` [a0, a1], ``scale`` b); ``shift`` [0, 0] with ``scale`` 1
is the identity.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.evaluation.posterior_quantiles import move, pit_z, row_levels

#: ridge penalty on the slope a1 (in units of rows; keeps a1 finite when medians barely vary)
RIDGE = 1.0
_KEYS = ("center", "spread", "shift", "scale")


def fit_location_shift(draws: np.ndarray, theta: np.ndarray, ridge: float = RIDGE) -> list[dict[str, Any]]:
    """Per parameter, the law N(a0 + a1 u, b^2) of the truth's normal score (:func:`pit_z`) given the
    row's standardised posterior median u, fitted by (ridge) least squares on rows ``draws`` (B, S, d)
    with truths ``theta`` (B, d)."""
    z = pit_z(draws, theta)
    med = np.median(np.asarray(draws, dtype=np.float64), axis=1)
    models = []
    for j in range(z.shape[1]):
        center, spread = float(med[:, j].mean()), float(max(med[:, j].std(), 1e-6))
        x = np.column_stack([np.ones(len(z)), (med[:, j] - center) / spread])
        a = np.linalg.solve(x.T @ x + np.diag([0.0, ridge]), x.T @ z[:, j])
        scale = float(np.sqrt(np.mean((z[:, j] - x @ a) ** 2)))
        models.append({"center": center, "spread": spread, "shift": [float(a[0]), float(a[1])],
                       "scale": max(scale, 1e-3)})
    return models


def _checked(model: Any, j: int) -> tuple[float, float, float, float, float]:
    ok = isinstance(model, dict) and all(k in model for k in _KEYS)
    try:
        vals = (float(model["center"]), float(model["spread"]), float(model["shift"][0]), float(model["shift"][1]),
                float(model["scale"])) if ok else ()
    except (TypeError, ValueError, IndexError, KeyError):
        vals = ()
    if len(vals) != 5 or not np.all(np.isfinite(vals)) or vals[1] <= 0 or vals[4] <= 0:
        raise InvphysError(f"the stored recalibration's location shift of parameter {j} is malformed: expected "
                           f"finite center, spread > 0, shift [a0, a1], scale > 0; got {model!r}")
    return vals  # type: ignore[return-value]


def apply_location_shift(draws: np.ndarray, models: list[Any]) -> np.ndarray:
    """Draws (B, S, d) whose marginal j in each row follows the fitted law: the draw at normal score z of
    its row's quantile function moves to score a0 + a1 u + b z (``None`` keeps a parameter)."""
    draws = np.asarray(draws, dtype=np.float64)
    if len(models) != draws.shape[2]:
        raise InvphysError(f"the stored location shift has {len(models)} parameters, the draws {draws.shape[2]}")
    med = np.median(draws, axis=1)  # every parameter's feature from the draws as given
    zl = row_levels(draws.shape[1])
    out = draws.copy()
    for j, model in enumerate(models):
        if model is None:
            continue
        center, spread, a0, a1, b = _checked(model, j)
        loc = a0 + a1 * (med[:, j] - center) / spread
        out[:, :, j] = move(draws[:, :, j], loc[:, None] + b * zl[None, :])
    return out
