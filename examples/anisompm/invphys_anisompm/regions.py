"""Regions of space: where bodies are sampled, which particles a grip holds, which grid nodes are held.

A region answers ``contains(points) -> bool mask`` for points of shape (N, 3) and has a bounding box
``bounds() -> (lo, hi)`` (used to place the sampling lattice). Regions compose with ``&`` (both), ``|``
(either) and ``-`` (the first without the second). All lengths in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _vec(v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    return a


class Region:
    """A set of points in space (subclasses define :meth:`contains` and :meth:`bounds`)."""

    def contains(self, points: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def __and__(self, other: Region) -> Region:
        return Intersection(self, other)

    def __or__(self, other: Region) -> Region:
        return Union(self, other)

    def __sub__(self, other: Region) -> Region:
        return Difference(self, other)


@dataclass(frozen=True, eq=False)
class Box(Region):
    """The axis-aligned box ``lo <= x <= hi``."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def contains(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        return np.all((p >= _vec(self.lo)) & (p <= _vec(self.hi)), axis=1)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return _vec(self.lo), _vec(self.hi)


@dataclass(frozen=True, eq=False)
class Ellipsoid(Region):
    """The ellipsoid ``sum(((x - centre) / radii)^2) <= 1`` (a sphere when the radii are equal)."""

    centre: tuple[float, float, float]
    radii: tuple[float, float, float]

    def contains(self, points: np.ndarray) -> np.ndarray:
        q = (np.asarray(points, dtype=np.float64) - _vec(self.centre)) / _vec(self.radii)
        return np.sum(q * q, axis=1) <= 1.0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        c, r = _vec(self.centre), _vec(self.radii)
        return c - r, c + r


def Sphere(centre, radius: float) -> Ellipsoid:
    """A sphere (an :class:`Ellipsoid` with equal radii)."""
    return Ellipsoid(tuple(_vec(centre)), (radius, radius, radius))


@dataclass(frozen=True, eq=False)
class HalfSpace(Region):
    """The points on the side of the plane through ``point`` that ``normal`` points away from:
    ``(x - point) . normal <= 0`` (so a ground plane with normal +y holds what is below it)."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]

    def contains(self, points: np.ndarray) -> np.ndarray:
        n = _vec(self.normal) / np.linalg.norm(self.normal)
        return (np.asarray(points, dtype=np.float64) - _vec(self.point)) @ n <= 0.0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(3, -np.inf), np.full(3, np.inf)


@dataclass(frozen=True, eq=False)
class Cylinder(Region):
    """The solid cylinder of ``radius`` around the axis through ``centre`` along coordinate ``axis``
    (0 = x, 1 = y, 2 = z), ``half_length`` either side of ``centre`` (a wire, a rod, a roller)."""

    centre: tuple[float, float, float]
    radius: float
    axis: int = 2
    half_length: float = 1.0

    def contains(self, points: np.ndarray) -> np.ndarray:
        q = np.asarray(points, dtype=np.float64) - _vec(self.centre)
        radial = np.delete(q, self.axis, axis=1)
        return (np.sum(radial * radial, axis=1) <= self.radius ** 2) & (np.abs(q[:, self.axis]) <= self.half_length)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        ext = np.full(3, self.radius)
        ext[self.axis] = self.half_length
        c = _vec(self.centre)
        return c - ext, c + ext


@dataclass(frozen=True, eq=False)
class Shell(Region):
    """The points of the ellipsoid ``outer`` within ``thickness`` of its surface: ``outer`` minus the
    same ellipsoid with radii shrunk by ``thickness`` (a skin, a rind)."""

    outer: Ellipsoid
    thickness: float

    def contains(self, points: np.ndarray) -> np.ndarray:
        r = _vec(self.outer.radii) - self.thickness
        core = Ellipsoid(self.outer.centre, tuple(np.maximum(r, 0.0)))
        return self.outer.contains(points) & ~core.contains(points)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.outer.bounds()


@dataclass(frozen=True, eq=False)
class Intersection(Region):
    a: Region
    b: Region

    def contains(self, points: np.ndarray) -> np.ndarray:
        return self.a.contains(points) & self.b.contains(points)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        (la, ha), (lb, hb) = self.a.bounds(), self.b.bounds()
        return np.maximum(la, lb), np.minimum(ha, hb)


@dataclass(frozen=True, eq=False)
class Union(Region):
    a: Region
    b: Region

    def contains(self, points: np.ndarray) -> np.ndarray:
        return self.a.contains(points) | self.b.contains(points)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        (la, ha), (lb, hb) = self.a.bounds(), self.b.bounds()
        return np.minimum(la, lb), np.maximum(ha, hb)


@dataclass(frozen=True, eq=False)
class Difference(Region):
    a: Region
    b: Region

    def contains(self, points: np.ndarray) -> np.ndarray:
        return self.a.contains(points) & ~self.b.contains(points)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.a.bounds()


class PointSet(Region):
    """Exactly the given points (N, 3), matched to ``tol`` metres: select particles one by one (a grip
    on particles chosen by another program, say)."""

    def __init__(self, points: np.ndarray, tol: float = 1e-9) -> None:
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.tol = float(tol)
        self._keys = {tuple(k) for k in np.round(self.points / self.tol).astype(np.int64)}

    def contains(self, points: np.ndarray) -> np.ndarray:
        keys = np.round(np.asarray(points, dtype=np.float64) / self.tol).astype(np.int64)
        return np.array([tuple(k) in self._keys for k in keys], dtype=bool)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)


def lattice(region: Region, spacing: float, origin: np.ndarray | None = None) -> np.ndarray:
    """Points (N, 3) of the regular lattice of ``spacing`` that lie inside ``region``; deterministic.

    The lattice points are cell centres ``origin + (i + 1/2) spacing``; ``origin`` defaults to the lower
    corner of the region's bounding box, so that a box whose sides are multiples of ``spacing`` holds
    exactly (side / spacing) points per side, each owning a cell of volume ``spacing^3``.
    """
    lo, hi = region.bounds()
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("lattice: the region is unbounded; intersect it with a Box first")
    o = lo if origin is None else _vec(origin)
    i0 = np.floor((lo - o) / spacing - 0.5).astype(np.int64)
    i1 = np.ceil((hi - o) / spacing - 0.5).astype(np.int64)
    axes = [o[a] + (np.arange(i0[a], i1[a] + 1) + 0.5) * spacing for a in range(3)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    return pts[region.contains(pts)]


__all__ = ["Box", "Cylinder", "Difference", "Ellipsoid", "HalfSpace", "Intersection", "PointSet", "Region", "Shell", "Sphere",
           "Union", "lattice"]
