"""Per-target random streams: an answer depends on (bundle, target, method, seed) alone.

Every random choice made while answering a target (posterior draws, optimiser runs, rollouts,
refinement) is seeded by :func:`target_seed`: a hash of the user's seed, the method's label, a
stream name and the target's own float64 values and mask. A target's position in a file or the size of
its batch never enters, so a file shuffled, reversed or cut into pieces gets the same answers.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError

#: seeds are whole numbers in [0, MAX_SEED]
MAX_SEED = 2**63 - 1


def check_seed(seed: Any) -> int:
    """``seed`` as an int, or :class:`InvphysError` (negative, too large, not a whole number)."""
    if not is_count(seed, 0, MAX_SEED):
        raise InvphysError(f"seed must be a whole number in 0 .. 2^63-1, got {seed!r}")
    return int(seed)


def target_seed(seed: int, method: str, values: np.ndarray, mask: np.ndarray, stream: str = "") -> int:
    """A 32-bit seed (what every optimiser accepts) for one target's ``stream`` under ``method`` and the user's ``seed``.

    The target enters as its float64 bytes (missing features as 0.0, -0.0 as 0.0) and its mask, so
    two targets that differ in any given feature, or in which features are given, get other streams.
    """
    mask = np.asarray(mask, dtype=bool).reshape(-1)
    vals = np.where(mask, np.asarray(values, dtype=np.float64).reshape(-1), 0.0) + 0.0  # -0.0 -> 0.0
    h = hashlib.sha256(b"invphys-target-seed-1\0")
    h.update(int(seed).to_bytes(8, "little", signed=False))
    h.update(method.encode() + b"\0" + stream.encode() + b"\0")
    h.update(np.ascontiguousarray(vals, dtype="<f8").tobytes())
    h.update(np.packbits(mask).tobytes() + len(mask).to_bytes(4, "little"))
    return int.from_bytes(h.digest()[:4], "little")


def target_rng(seed: int, method: str, values: np.ndarray, mask: np.ndarray, stream: str = "") -> np.random.Generator:
    """A NumPy generator on :func:`target_seed`'s stream."""
    return np.random.default_rng(target_seed(seed, method, values, mask, stream))
