"""Surrogate error bars that mean what they say: the ensemble's spread scaled to its real errors.

An ensemble's members disagree less than the surrogate errs (on the shipped paper bundle, a ±1.645 sigma
band of its std holds about 63 % of held-out errors, not 90 %). :func:`fit_error_scales` finds, per
feature k, the factor c_k that makes ``|mean_k - y_k| <= 1.645 c_k std_k`` hold on 90 % of one set of
held-out rows (the 90 % quantile of ``|error| / std``); :func:`error_bar_coverage` checks any scaling on
another set. :func:`calibrated_feature_std` is what an answer reports: ``std * c`` (the raw spread when the
bundle holds no diagnostics).
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: the stated interval: ± Z90 sigma holds 90 % of a normal error
Z90 = 1.6448536269514722
NOMINAL = 0.90


def ratios(mean: np.ndarray, std: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N, M) |mean - y| / std (inf where the members agree exactly and the error is not 0)."""
    err = np.abs(np.asarray(mean, dtype=np.float64) - np.asarray(y, dtype=np.float64))
    s = np.asarray(std, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(s > 0, err / np.where(s > 0, s, 1.0), np.where(err > 0, np.inf, 0.0))
    return r


def fit_error_scales(mean: np.ndarray, std: np.ndarray, y: np.ndarray, nominal: float = NOMINAL) -> np.ndarray:
    """(M,) factors c_k with ``|error_k| <= Z c_k std_k`` on a share ``nominal`` of the rows (Z for that share)."""
    from scipy.stats import norm

    z = float(norm.ppf(0.5 + nominal / 2))
    r = ratios(mean, std, y)
    return np.array([float(np.quantile(r[np.isfinite(y[:, k]), k], nominal)) / z for k in range(r.shape[1])])


def error_bar_coverage(mean: np.ndarray, std: np.ndarray, y: np.ndarray, scales: np.ndarray | None = None,
                       z: float = Z90) -> dict[str, Any]:
    """Share of held-out errors inside ±z (c_k) std_k: per feature and over all (row, feature) pairs."""
    c = np.ones(np.asarray(y).shape[1]) if scales is None else np.asarray(scales, dtype=np.float64)
    inside = ratios(mean, std, y) <= z * c[None, :]
    return {"overall": float(inside.mean()), "per_feature": inside.mean(axis=0).tolist()}


def calibrated_feature_std(std: np.ndarray, diagnostics: dict[str, Any] | None, feature_names: Any = None
                           ) -> np.ndarray:
    """The ensemble's std (B, M) scaled by the bundle's stored factors (``surrogate_error_scales`` of
    its diagnostics), so that ±1.645 of it holds 90 % of the surrogate's errors; unscaled without them."""
    std = np.asarray(std, dtype=np.float64)
    block = (diagnostics or {}).get("surrogate_error_scales")
    if not block:
        return std
    if feature_names is not None and list(block["features"]) != list(feature_names):
        raise ValueError("the diagnostics' surrogate error scales are for other features")
    return std * np.asarray(block["scales"], dtype=np.float64)
