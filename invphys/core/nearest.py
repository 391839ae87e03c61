"""The ``k`` nearest of many rows by their squared distances: nearest first, ties by the lower index."""

from __future__ import annotations

import numpy as np


def nearest_first(d2: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` smallest of ``d2`` (N,), smallest first, ties by the lower index: exactly a
    stable argsort's first ``k``, without sorting all N (every value tied with the k-th is kept until the
    tie is broken by index)."""
    d2 = np.asarray(d2)
    k = min(int(k), len(d2))
    if k <= 0:
        return np.empty(0, dtype=np.intp)
    if k < len(d2):
        kth = np.partition(d2, k - 1)[k - 1]
        cand = np.flatnonzero(d2 <= kth)
    else:
        cand = np.arange(len(d2))
    return cand[np.argsort(d2[cand], kind="stable")][:k]
