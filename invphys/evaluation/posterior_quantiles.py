"""Each row's posterior marginals as quantile functions in logit space, read at normal scores.

A row's S draws of one parameter, sorted, are its quantile function at the normal scores of the levels
(i + 0.5) / S (:func:`row_levels`), in logit space so that every value read from it stays inside the
parameter box, and continued past the extreme draws with slope = the logit draws' std (a normal tail).
:func:`pit_z` reads the truth's score from it; :func:`move` re-reads draws at other scores, keeping
their order (hence the posterior's dependence between parameters).
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-6


def logit(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(x, dtype=np.float64), _EPS, 1.0 - _EPS)
    return np.log(x) - np.log1p(-x)


def extrap(x: np.ndarray, xp: np.ndarray, fp: np.ndarray, lo_slope: float, hi_slope: float) -> np.ndarray:
    """``np.interp`` continued linearly beyond the ends with the given slopes (df/dx)."""
    y = np.interp(x, xp, fp)
    y = np.where(x < xp[0], fp[0] - (xp[0] - x) * lo_slope, y)
    return np.where(x > xp[-1], fp[-1] + (x - xp[-1]) * hi_slope, y)


def row_levels(s: int) -> np.ndarray:
    """Normal scores of the levels (i + 0.5) / s of a row's sorted draws (``ndtri`` is ``scipy.stats.norm.ppf``'s
    own function, without importing ``scipy.stats``, most of a second of a one-target answer's start)."""
    from scipy.special import ndtri

    return np.asarray(ndtri((np.arange(s) + 0.5) / s))


def check(draws: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    draws = np.asarray(draws, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    if draws.ndim != 3 or theta.shape != (draws.shape[0], draws.shape[2]):
        raise ValueError(f"draws (B, S, d) and theta (B, d) expected, got {draws.shape} and {theta.shape}")
    return draws, theta


def pit_z(draws: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(B, d) the truth's normal score under each row's marginal, continuous also beyond the draws.
    A calibrated posterior gives scores distributed N(0, 1)."""
    draws, theta = check(draws, theta)
    b, s, d = draws.shape
    zl = row_levels(s)
    ld, lt = np.sort(logit(draws), axis=1), logit(theta)
    sd = np.maximum(ld.std(axis=1), 1e-6)  # (B, d)
    out = np.empty((b, d))
    for i in range(b):
        for j in range(d):
            xp, ok = np.unique(ld[i, :, j], return_index=True)
            out[i, j] = extrap(lt[i:i + 1, j], xp, zl[ok], 1 / sd[i, j], 1 / sd[i, j])[0]
    return out


def move(column: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Draws of one parameter (B, S) re-read from each row's quantile function: the draw of rank k moves
    to the value at normal score ``scores[k]`` (``scores`` (S,) for every row, or (B, S) per row).
    Ranks are kept; values stay strictly inside the box."""
    column = np.asarray(column, dtype=np.float64)
    b, s = column.shape
    zl = row_levels(s)
    scores = np.broadcast_to(np.asarray(scores, dtype=np.float64), (b, s))
    order = np.argsort(column, axis=1, kind="stable")
    ld = np.take_along_axis(logit(column), order, axis=1)
    sd = np.maximum(ld.std(axis=1), 1e-6)
    moved = np.empty((b, s))
    for i in range(b):
        moved[i] = extrap(scores[i], zl, ld[i], sd[i], sd[i])
    from scipy.special import expit  # the logistic without exp's overflow warning for far-out scores

    out = np.empty((b, s))
    np.put_along_axis(out, order, expit(moved), axis=1)
    return out
