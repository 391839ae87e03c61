"""Seeded designs of experiments in the unit hypercube [0, 1]^d.

Four samplers, all deterministic for a given ``(n, dim, seed)``:

* ``uniform``: i.i.d. uniform points (the paper's choice). Prefix-stable: the first ``n`` points of a
  design of ``n' > n`` points are the design of ``n`` points, so growing a dataset's ``n`` and
  re-running only simulates the new points.
* ``sobol``: a scrambled Sobol' sequence (low discrepancy). Also prefix-stable.
* ``lhs``: a Latin hypercube (each of the ``n`` strata of every axis holds exactly one point). Not
  prefix-stable: changing ``n`` changes every point.
* ``edge``: every coordinate uniform in the outer 10 % of its range, at either end (a corner region of the
  box, where surrogates and posteriors fail first): the evaluation protocol's user-like edge targets.
  Prefix-stable.
"""

from __future__ import annotations

import warnings

import numpy as np

from invphys.core.errors import InvphysError, did_you_mean

SAMPLERS: tuple[str, ...] = ("uniform", "sobol", "lhs", "edge")
#: ``edge``: every coordinate uniform in the outer ``EDGE_BAND`` of its range (either end), where surrogates and
#: posteriors fail first; the evaluation protocol's user-like edge targets
EDGE_BAND = 0.1


def sample_unit(n: int, dim: int, method: str = "uniform", seed: int = 0) -> np.ndarray:
    """``n`` points of ``[0, 1]^dim`` (shape ``(n, dim)``, float64) drawn by ``method``.

    Raises :class:`InvphysError` for an unknown method or non-positive sizes.
    """
    if method not in SAMPLERS:
        raise InvphysError(f"unknown sampler {method!r}.{did_you_mean(method, SAMPLERS)} "
                           f"Samplers: {', '.join(SAMPLERS)}")
    if n < 0 or dim <= 0:
        raise InvphysError(f"cannot sample {n} points in {dim} dimensions")
    if n == 0:
        return np.zeros((0, dim))
    if method == "uniform":
        return np.random.default_rng(seed).random((n, dim))
    if method == "edge":
        r = np.random.default_rng(seed).random((n, dim, 2))  # (offset, side) per coordinate: prefix-stable
        offset = r[..., 0] * EDGE_BAND
        return np.where(r[..., 1] < 0.5, offset, 1.0 - offset)
    from scipy.stats import qmc

    if method == "sobol":
        engine = qmc.Sobol(d=dim, scramble=True, seed=np.random.default_rng(seed))
        with warnings.catch_warnings():
            # balance properties need n = 2^m; any prefix is still a valid low-discrepancy design
            warnings.simplefilter("ignore", UserWarning)
            points = engine.random(n)
    else:
        points = qmc.LatinHypercube(d=dim, seed=np.random.default_rng(seed)).random(n)
    return np.clip(np.asarray(points, dtype=np.float64), 0.0, 1.0)
