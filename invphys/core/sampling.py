"""Seeded designs of experiments in the unit hypercube [0, 1]^d.

Five samplers, all deterministic for a given ``(n, dim, seed)``:

* ``uniform``: i.i.d. uniform points (the paper's choice). Prefix-stable: the first ``n`` points of a
  design of ``n' > n`` points are the design of ``n`` points, so growing a dataset's ``n`` and
  re-running only simulates the new points.
* ``sobol``: a scrambled Sobol' sequence (low discrepancy). Also prefix-stable.
* ``lhs``: a Latin hypercube (each of the ``n`` strata of every axis holds exactly one point). Not
  prefix-stable: changing ``n`` changes every point.
* ``edge``: every coordinate uniform in the outer 10 % of its range, at either end (a corner region of the
  box, where surrogates and posteriors fail first): the evaluation protocol's user-like edge targets.
  Prefix-stable.
* ``faces``: each coordinate independently in the outer 10 % band (either end) with probability 1/2, uniform
  over the whole range otherwise: points on and near the box's faces, edges and corners of every dimension,
  where uniform designs put almost nothing (an adaptive design's choice for where answers fail). Prefix-stable.

``edge`` and ``faces`` are not draws from the box prior: their densities are :func:`unit_density`.
"""

from __future__ import annotations

import warnings

import numpy as np

from invphys.core.errors import InvphysError, did_you_mean

SAMPLERS: tuple[str, ...] = ("uniform", "sobol", "lhs", "edge", "faces")
#: ``edge``: every coordinate uniform in the outer ``EDGE_BAND`` of its range (either end), where surrogates and
#: posteriors fail first; the evaluation protocol's user-like edge targets
EDGE_BAND = 0.1
#: ``faces``: the probability that a coordinate lies in the outer band
FACES_EDGE_SHARE = 0.5


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
    if method == "faces":
        r = np.random.default_rng(seed).random((n, dim, 3))  # (in band?, offset, side) per coordinate
        band = np.where(r[..., 2] < 0.5, r[..., 1] * EDGE_BAND, 1.0 - r[..., 1] * EDGE_BAND)
        return np.where(r[..., 0] < FACES_EDGE_SHARE, band, r[..., 1])
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


def unit_density(x: np.ndarray, method: str) -> np.ndarray:
    """The density of ``method``'s design at points ``x`` of ``[0, 1]^d`` (shape ``(n, d)``; 1 everywhere for
    the box prior's samplers ``uniform``, ``sobol``, ``lhs``), e.g. to weigh rows of a non-prior design back
    to the prior."""
    if method not in SAMPLERS:
        raise InvphysError(f"unknown sampler {method!r}.{did_you_mean(method, SAMPLERS)} "
                           f"Samplers: {', '.join(SAMPLERS)}")
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    in_band = (x <= EDGE_BAND) | (x >= 1.0 - EDGE_BAND)
    if method == "edge":
        return np.prod(np.where(in_band, 0.5 / EDGE_BAND, 0.0), axis=1)
    if method == "faces":
        per = (1.0 - FACES_EDGE_SHARE) + np.where(in_band, FACES_EDGE_SHARE * 0.5 / EDGE_BAND, 0.0)
        return np.prod(per, axis=1)
    return np.ones(len(x))
