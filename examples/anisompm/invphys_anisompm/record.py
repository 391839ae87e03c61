"""The output of one simulated run: :class:`RunRecord` (shared by lock-step and streamed runs)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class RunRecord:
    """One run's output. Per-frame ``series`` have ``frames + 1`` entries (frame 0 = the settled state).

    Series: ``max_speed`` (m/s), ``kinetic_energy`` (J), ``centroid/<body>`` (3, m),
    ``mean_damage/<body>``, ``force/<object>`` (3, N: the mean force the material exerts on a collider
    or grip over the frame; frame 0 holds the last settling frame's), ``work/<object>`` (J done on the
    material since frame 0), ``position/<object>`` (3, m: the object's displacement), and each host
    reduction's name.
    """

    positions: list[np.ndarray] = field(default_factory=list)
    damage: list[np.ndarray] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    series: dict[str, list] = field(default_factory=dict)
    substeps: int = 0
    settle_substeps: int = 0
    dt: float = 0.0
    guard_frames: int = 0
    failure: str | None = None
    wall_time_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.failure is None

    def series_array(self, name: str) -> np.ndarray:
        return np.asarray(self.series[name], dtype=np.float64)


__all__ = ["RunRecord"]
