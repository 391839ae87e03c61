"""Kinematic paths of colliders and grips: displacement from the start as a function of time.

A path is the same for every run of a batch (it belongs to the scene, not to the parameters). Time
``t = 0`` is the first recorded frame (after settling); during settling every kinematic object rests at
its start. The engine gives a kinematic object, over a substep from ``t0`` to ``t1``, the displacement
``path(t1)`` and the velocity ``(path(t1) - path(t0)) / (t1 - t0)``, so positions never drift.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


class Path:
    """Displacement (m) from the start at time(s) ``t`` (s): ``displacement(t) -> (..., 3)``."""

    def displacement(self, t: np.ndarray | float) -> np.ndarray:
        raise NotImplementedError

    def peak_speed(self, t_end: float, samples: int = 2001) -> float:
        """The largest speed (m/s) on [0, t_end] (finite differences over ``samples`` points)."""
        if t_end <= 0:
            return 0.0
        ts = np.linspace(0.0, t_end, samples)
        p = self.displacement(ts)
        return float(np.max(np.linalg.norm(np.diff(p, axis=0), axis=1) / np.diff(ts)))


@dataclass(frozen=True)
class Static(Path):
    """At rest."""

    def displacement(self, t: np.ndarray | float) -> np.ndarray:
        return np.zeros((*np.shape(t), 3))


def smoothstep(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


@dataclass(frozen=True)
class Waypoints(Path):
    """Through ``points`` (K, 3) (displacements; the first is usually 0) at ``times`` (K,), at rest before
    the first and after the last. ``ease`` (s) rounds each corner: velocity changes over that long
    instead of at once (0 = piecewise linear), which keeps the engine's forces free of kicks."""

    times: tuple[float, ...]
    points: tuple[tuple[float, float, float], ...]
    ease: float = 0.0

    def __post_init__(self) -> None:
        t = np.asarray(self.times, float)
        if len(t) < 1 or np.any(np.diff(t) <= 0) or np.asarray(self.points, float).shape != (len(t), 3):
            raise ValueError("Waypoints: times must increase and points must be (len(times), 3)")

    def _linear(self, t: np.ndarray) -> np.ndarray:
        tt = np.asarray(self.times, float)
        pts = np.asarray(self.points, float)
        return np.stack([np.interp(t, tt, pts[:, a]) for a in range(3)], axis=-1)

    def displacement(self, t: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        if self.ease <= 0:
            return self._linear(t)
        # average of the piecewise-linear path over a window of width `ease` (a box filter): C1 corners
        offsets = (np.arange(8) + 0.5) / 8 - 0.5
        return np.mean([self._linear(t + self.ease * o) for o in offsets], axis=0)


def linear_cut(direction, distance: float, speed: float, t_start: float = 0.0, ease: float = 0.0) -> Waypoints:
    """Move ``distance`` (m) along ``direction`` at ``speed`` (m/s), starting at ``t_start`` (s)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    t1 = t_start + distance / speed
    times = (t_start, t1) if t_start > 0 else (0.0, t1)
    pts = ((0.0, 0.0, 0.0), tuple(d * distance))
    if t_start > 0:
        times, pts = (0.0, t_start, t1), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), tuple(d * distance))
    return Waypoints(times=times, points=pts, ease=ease)


@dataclass(frozen=True)
class FunctionPath(Path):
    """Any path given as a function ``fn(t) -> (..., 3)`` of displacements (``fn(0)`` is subtracted)."""

    fn: Callable[[np.ndarray], np.ndarray] = field(compare=False)

    def displacement(self, t: np.ndarray | float) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return np.asarray(self.fn(t), float) - self._origin()

    def _origin(self) -> np.ndarray:
        """``fn(0)``, evaluated once (kinematic tables ask for displacements at every frame of every run)."""
        origin = self.__dict__.get("_origin_value")
        if origin is None:
            origin = np.asarray(self.fn(np.zeros(())), float)
            object.__setattr__(self, "_origin_value", origin)   # a cache on a frozen dataclass: not a field
        return origin


__all__ = ["FunctionPath", "Path", "Static", "Waypoints", "linear_cut", "smoothstep"]
