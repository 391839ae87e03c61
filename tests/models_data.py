"""Data for the model tests: the committed real orange-peel fixture and a smooth synthetic function."""

from __future__ import annotations

from pathlib import Path

import numpy as np

FIXTURE = Path(__file__).resolve().parent / "data" / "orange_tiny.npz"


def orange_tiny() -> dict[str, np.ndarray]:
    """``tests/data/orange_tiny.npz``: real tiny-preset orange-peel runs (theta, params, y, names)."""
    with np.load(FIXTURE, allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


def orange_split(seed: int = 0, test_fraction: float = 0.2):
    """(theta_train, y_train, theta_test, y_test) of the fixture, a seeded 80/20 split."""
    d = orange_tiny()
    n = len(d["theta"])
    perm = np.random.default_rng(seed).permutation(n)
    n_test = round(n * test_fraction)
    te, tr = np.sort(perm[:n_test]), np.sort(perm[n_test:])
    return d["theta"][tr], d["y"][tr], d["theta"][te], d["y"][te]


def smooth(n: int, d: int = 9, seed: int = 0, low: float = 0.0, high: float = 1.0):
    """A smooth 5-output function of theta drawn uniformly from [low, high]^d."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(low, high, size=(n, d))
    y = np.stack([np.sin(3 * t[:, 0]) + t[:, 1] ** 2, t[:, 2] * t[:, 3] + 0.5 * t[:, 4], np.exp(t[:, 5]),
                  np.cos(2 * t[:, 6] + t[:, 7]) * t[:, 8], t[:, 0] + t[:, 8]], axis=1)
    return t, y
