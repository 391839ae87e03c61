"""Held-out target selection: farthest-point sampling in standardised feature space (paper sec. 3.6).

The paper evaluates on 20 diverse targets chosen by farthest-point sampling from the test partition
and validates the first 10 through the simulator. Sampling is greedy and deterministic: it starts at
the point closest to the features' mean (or at ``start``), then repeatedly adds the point whose
distance to the chosen set is largest, so that the first ``k`` of ``n`` targets are themselves a
farthest-point selection of size ``k``.
"""

from __future__ import annotations

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.standardiser import Standardiser


def standardise(y: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """z-scores of ``y`` (N, M) with the mean/std of ``reference`` (default ``y``); constant features -> 0."""
    y = np.asarray(y, dtype=np.float64)
    ref = y if reference is None else np.asarray(reference, dtype=np.float64)
    return Standardiser.fit(ref).transform(y)


def farthest_point_indices(y: np.ndarray, n: int, reference: np.ndarray | None = None,
                           start: int | None = None) -> np.ndarray:
    """Indices (n,) into ``y`` (N, M) of ``n`` farthest-point samples in standardised feature space.

    Args:
        y: candidate features, e.g. the test partition's.
        n: how many to choose (1 <= n <= N).
        reference: features whose mean/std standardise ``y`` (default ``y`` itself).
        start: index of the first point; default the point closest to the mean.
    """
    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 2 or y.shape[0] == 0:
        raise InvphysError(f"target selection needs a non-empty (N, M) feature array, got shape {y.shape}")
    if not 1 <= n <= y.shape[0]:
        raise InvphysError(f"cannot choose {n} targets from {y.shape[0]} candidates "
                           f"(lower targets.n or enlarge the test partition)")
    finite = np.all(np.isfinite(y), axis=1)
    if not finite.all():
        if finite.sum() < n:
            raise InvphysError(f"only {int(finite.sum())} candidates have finite features; {n} asked")
    z = standardise(np.where(np.isfinite(y), y, 0.0), reference)
    if start is None:
        d0 = np.where(finite, np.linalg.norm(z, axis=1), np.inf)
        start = int(np.argmin(d0))
    chosen = [int(start)]
    dist = np.linalg.norm(z - z[start], axis=1)
    dist[~finite] = -np.inf
    dist[start] = -np.inf
    for _ in range(n - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(z - z[nxt], axis=1))
        dist[chosen] = -np.inf
        dist[~finite] = -np.inf
    return np.asarray(chosen, dtype=np.int64)


#: the evaluation protocol's two held-out sets: farthest-point first, then uniformly random ones
PROTOCOL_SELECTION = "farthest_point+random"


def protocol_split(n: int) -> int:
    """How many of ``n`` protocol targets are farthest-point (the first ``ceil(n / 2)``; the rest random)."""
    return (int(n) + 1) // 2


def target_set_labels(n: int, selection: str) -> list[str]:
    """The set each of ``n`` selected targets belongs to (``"farthest_point"`` or ``"random"``)."""
    if selection == PROTOCOL_SELECTION:
        k = protocol_split(n)
        return ["farthest_point"] * k + ["random"] * (int(n) - k)
    return [selection] * int(n)


def select_targets(y: np.ndarray, test_idx: np.ndarray, n: int, selection: str = "farthest_point",
                   seed: int = 0) -> np.ndarray:
    """Dataset row indices of ``n`` targets from the test partition ``test_idx``.

    ``selection`` is ``"farthest_point"`` (standardised with the whole dataset's statistics),
    ``"random"`` (seeded), or ``"farthest_point+random"`` (the evaluation protocol: the first
    ``ceil(n / 2)`` by farthest-point sampling, then the rest uniformly at random from the remaining
    test rows; :func:`target_set_labels` names each one's set).
    """
    test_idx = np.asarray(test_idx, dtype=np.int64)
    y = np.asarray(y, dtype=np.float64)
    n = min(int(n), len(test_idx))
    if n < 1:
        raise InvphysError("the test partition is empty: no held-out targets to invert")
    if selection == "farthest_point":
        return test_idx[farthest_point_indices(y[test_idx], n, reference=y)]
    if selection == "random":
        rng = np.random.default_rng(seed)
        return np.sort(rng.choice(test_idx, size=n, replace=False))
    if selection == PROTOCOL_SELECTION:
        k = protocol_split(n)
        fp = test_idx[farthest_point_indices(y[test_idx], k, reference=y)]
        rest = np.setdiff1d(test_idx, fp)
        rng = np.random.default_rng(seed)
        rnd = np.sort(rng.choice(rest, size=min(n - k, len(rest)), replace=False))
        return np.concatenate([fp, rnd]).astype(np.int64)
    raise InvphysError(f"unknown target selection {selection!r}; choose farthest_point, random or "
                       f"{PROTOCOL_SELECTION}")
