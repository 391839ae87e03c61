"""Does the surrogate ensemble know where it is wrong? Rank correlation of its std with real errors."""

from __future__ import annotations

from typing import Any

import numpy as np

from invphys.evaluation.stats import spearman
from invphys.evaluators.uncertainty import normalised_std


def uncertainty_check(surrogate: Any, theta: np.ndarray, y: np.ndarray, scales: np.ndarray,
                      feature_names: list[str] | None = None, answers: list[dict[str, Any]] | None = None
                      ) -> dict[str, Any]:
    """Spearman correlations between the ensemble's std and the surrogate's real errors.

    On held-out rows (``theta`` (N, d), true features ``y`` (N, M)): per row, the normalised std
    ``sqrt(mean_k (std_k / s_k)^2)`` against the normalised error ``sqrt(mean_k ((mean_k - y_k) / s_k)^2)``,
    and per feature std_k against |mean_k - y_k|. On validated answers (rows with ``theta`` and a finite
    ``gap``): the normalised std at the answer against |R_surr - R_actual|. A surrogate without
    uncertainty (all std 0) gives ``available: False``.
    """
    theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
    y = np.atleast_2d(np.asarray(y, dtype=np.float64))
    scales = np.asarray(scales, dtype=np.float64)
    mean, std = surrogate.predict_with_uncertainty(theta)
    if not np.any(np.asarray(std) > 0):
        return {"available": False, "note": f"surrogate {getattr(surrogate, 'name', '?')!r} gives no uncertainty "
                                           f"(use type: ensemble)"}
    err = np.sqrt(np.mean(((mean - y) / scales) ** 2, axis=1))
    u = normalised_std(std, scales)
    names = feature_names or [f"y{k}" for k in range(y.shape[1])]
    out: dict[str, Any] = {
        "available": True, "n_rows": len(theta), "spearman_rows": spearman(u, err),
        "mean_normalised_std": float(u.mean()), "mean_normalised_error": float(err.mean()),
        "spearman_per_feature": {n: spearman(std[:, k], np.abs(mean[:, k] - y[:, k])) for k, n in enumerate(names)}}
    val = [r for r in answers or [] if r.get("gap") is not None and np.isfinite(r["gap"]) and r.get("theta")]
    if len(val) >= 3:
        th = np.array([r["theta"] for r in val], dtype=np.float64)
        _, s_ans = surrogate.predict_with_uncertainty(th)
        out["n_answers"] = len(val)
        out["spearman_answers"] = spearman(normalised_std(s_ans, scales), np.abs([r["gap"] for r in val]))
    return out
