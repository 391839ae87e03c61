"""Training-data checks, fingerprints and R^2 metrics (NumPy only)."""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError


class TrainingDataError(InvphysError, ValueError):
    """Training or prediction input has the wrong shape, non-finite values or too few rows."""


class NotFittedError(InvphysError, RuntimeError):
    """A model was used (predict, encode, save) before it was fitted or loaded."""


class ModelLoadError(InvphysError, OSError):
    """A saved model directory is missing, incomplete or holds a different model."""


#: fewest rows a model can be trained on (a train and a validation part are both needed)
MIN_ROWS = 8


def check_training_data(theta: Any, y: Any, name: str = "model") -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert ``theta`` (N, d) in [0, 1] and ``y`` (N, M); return float64 copies."""
    theta = np.asarray(theta, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if theta.ndim != 2 or y.ndim != 2:
        raise TrainingDataError(
            f"{name}: theta and y must be 2-D arrays (N, d) and (N, M), got shapes {theta.shape} and {y.shape}")
    if theta.shape[0] != y.shape[0]:
        raise TrainingDataError(f"{name}: theta has {theta.shape[0]} rows but y has {y.shape[0]}")
    if theta.shape[0] < MIN_ROWS:
        raise TrainingDataError(f"{name}: needs at least {MIN_ROWS} rows to train, got {theta.shape[0]}")
    if theta.shape[1] == 0 or y.shape[1] == 0:
        raise TrainingDataError(f"{name}: theta and y need at least one column each")
    for label, arr in (("theta", theta), ("y", y)):
        bad = ~np.isfinite(arr)
        if bad.any():
            rows = np.unique(np.nonzero(bad)[0])[:5].tolist()
            raise TrainingDataError(f"{name}: {label} has non-finite values (rows {rows}...)")
    if theta.min() < -1e-6 or theta.max() > 1 + 1e-6:
        raise TrainingDataError(
            f"{name}: theta must be normalised to [0, 1] (got range [{theta.min():.3g}, {theta.max():.3g}]); "
            "pass normalised parameters, not physical ones")
    return theta, y


def check_input(x: Any, dim: int, label: str, name: str) -> np.ndarray:
    """``x`` as a (B, dim) float32 array (a single (dim,) vector becomes one row)."""
    arr = np.asarray(x, dtype=np.float32)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise TrainingDataError(f"{name}: {label} must have shape (B, {dim}), got {np.shape(x)}")
    return arr


def array_fingerprint(*arrays: np.ndarray) -> str:
    """A short stable hash of arrays' shapes and float64 values (the data a model was trained on)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def r2_scores(y_true: np.ndarray, y_pred: np.ndarray) -> tuple[float, list[float]]:
    """(overall, per-feature) coefficient of determination.

    Per feature: ``1 - SS_res / SS_tot``; overall: the mean of the per-feature values (sklearn's
    ``r2_score(multioutput="uniform_average")``). A constant feature scores 1 if predicted exactly,
    else 0.
    """
    y_true = np.asarray(y_true, dtype=np.float64)
    y_pred = np.asarray(y_pred, dtype=np.float64)
    ss_res = ((y_true - y_pred) ** 2).sum(axis=0)
    ss_tot = ((y_true - y_true.mean(axis=0)) ** 2).sum(axis=0)
    per = np.where(ss_tot > 0, 1.0 - ss_res / np.where(ss_tot > 0, ss_tot, 1.0),
                   np.where(ss_res <= 1e-12, 1.0, 0.0))
    return float(per.mean()), [float(v) for v in per]


def split_indices(n: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A seeded random (train, validation) split of ``range(n)``; both parts non-empty."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    n_val = round(n * val_fraction)
    n_val = min(max(n_val, 1), n - 1)
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])

