"""Bootstrap confidence intervals for means and paired differences over targets."""

from __future__ import annotations

import numpy as np


def bootstrap_mean_ci(values: np.ndarray, n_boot: int = 2000, confidence: float = 0.95,
                      seed: int = 0) -> tuple[float, float, float]:
    """(mean, lo, hi): the mean of finite ``values`` and its percentile-bootstrap interval.

    Targets are resampled with replacement ``n_boot`` times. NaN when no value is finite; a single
    value gives a zero-width interval.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return float("nan"), float("nan"), float("nan")
    mean = float(v.mean())
    if len(v) == 1:
        return mean, mean, mean
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(v), size=(int(n_boot), len(v)))
    means = v[idx].mean(axis=1)
    alpha = (1.0 - confidence) / 2.0
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha])
    return mean, float(lo), float(hi)


def mean_with_ci(values: np.ndarray, n_boot: int = 2000, confidence: float = 0.95,
                 seed: int = 0) -> dict[str, float | list[float]]:
    """``{"mean", "ci95": [lo, hi]}`` of :func:`bootstrap_mean_ci`, as reports and benchmark JSONs store it."""
    mean, lo, hi = bootstrap_mean_ci(values, n_boot, confidence, seed)
    return {"mean": mean, "ci95": [lo, hi]}


def paired_difference(a: np.ndarray, b: np.ndarray, n_boot: int = 2000, confidence: float = 0.95,
                      seed: int = 0) -> dict[str, float | int | bool]:
    """Mean of ``a - b`` over the targets where both are finite, with its bootstrap interval.

    ``beats`` is True only when the interval's lower end is above 0 (the protocol's rule).
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"paired difference of {a.shape} and {b.shape} values")
    ok = np.isfinite(a) & np.isfinite(b)
    mean, lo, hi = bootstrap_mean_ci(a[ok] - b[ok], n_boot, confidence, seed)
    return {"n": int(ok.sum()), "mean_diff": mean, "ci95": [lo, hi], "beats": bool(np.isfinite(lo) and lo > 0)}


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation of the finite pairs (NaN with fewer than 3 or a constant side)."""
    from scipy.stats import spearmanr

    x = np.asarray(x, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return float("nan")
    return float(spearmanr(x[ok], y[ok]).statistic)
