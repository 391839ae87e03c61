"""The 13 behavioural features of a cheese-cutting run (exact definitions: docs/cheese-cut/index.md).

Most features read the per-frame time series of the run (the wire's force, depth and work, the board's
load, the damage and column-drop series); ``damage_band_width`` reads the last particle frame. End-of-run values are
averaged over the last ``tail_frames`` frames, and threshold crossings are interpolated, so that every
feature changes smoothly with the parameters.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import FeatureExtractor, PluginConfig
from invphys.core.results import Trajectory
from invphys_cheese_cut.scene import BLOCK, GAP

#: feature name -> unit
FEATURE_UNITS: dict[str, str] = {
    "peak_force": "N",
    "mean_cut_force": "N",
    "cut_work": "log10 J",
    "contact_stiffness": "log10 N/m",
    "fracture_onset_depth": "m",
    "final_mean_damage": "",
    "damaged_fraction": "",
    "peak_column_drop": "m",
    "resting_load": "N",
    "settle_drop": "m",
    "force_ratio": "",
    "damage_band_width": "m",
    "slice_drag_ratio": "",
}
FEATURE_NAMES: tuple[str, ...] = tuple(FEATURE_UNITS)
NEEDED_SERIES = ("wire_force", "wire_drag", "wire_depth", "wire_work", "board_force", "mean_damage", "damaged_fraction",
                 "column_drop", "sag")


class TrajectoryError(InvphysError, ValueError):
    """A trajectory that cannot be summarised (missing series, non-finite values)."""


def top_mean(values: np.ndarray, k: int) -> float:
    """Mean of the ``k`` largest values (a robust, smooth maximum)."""
    v = np.sort(np.asarray(values, float))
    return float(v[-k:].mean()) if v.size else 0.0


def first_crossing(x: np.ndarray, y: np.ndarray, level: float) -> float | None:
    """The x at which ``y`` first reaches ``level`` (linear interpolation), or None."""
    hit = np.flatnonzero(y >= level)
    if len(hit) == 0:
        return None
    k = int(hit[0])
    if k == 0:
        return float(x[0])
    a, b = float(y[k - 1]), float(y[k])
    return float(x[k - 1] + (x[k] - x[k - 1]) * ((level - a) / (b - a) if b > a else 1.0))


class CheeseCutFeatures(FeatureExtractor):
    """Thirteen features of a wire cut: forces (peak, mean, contact stiffness, work, resting load, late/peak
    ratio), fracture (onset depth, mean damage, broken fraction, damage band width), and shape (settling
    drop, how far the cheese under the wire is pushed down), and friction (drag along the wire / push)."""

    name: ClassVar[str] = "cheese_cut_features"

    class Config(PluginConfig):
        """Settings of the cheese-cut features."""

        onset_level: float = Field(0.02, gt=0, lt=1, description="mean damage that marks fracture onset")
        tail_frames: int = Field(3, ge=1, description="end-of-run values are averaged over this many frames")
        peak_frames: int = Field(3, ge=1, description="peak force = mean of this many largest frame forces")
        contact_depth: float = Field(0.25, gt=0, le=1, description="stiffness fit up to this fraction of "
                                                                   "the block's height of wire depth")

    @property
    def feature_names(self) -> tuple[str, ...]:
        return FEATURE_NAMES

    @property
    def feature_units(self) -> tuple[str, ...]:
        return tuple(FEATURE_UNITS.values())

    def extract(self, trajectory: Trajectory) -> np.ndarray:
        c = self.config
        missing = [s for s in NEEDED_SERIES if s not in trajectory.series]
        if missing:
            raise TrajectoryError(f"cheese-cut trajectory lacks the series {', '.join(missing)}")
        s = {k: trajectory.series[k].values.astype(np.float64) for k in NEEDED_SERIES}
        if not all(np.all(np.isfinite(v)) for v in s.values()):
            raise TrajectoryError("cheese-cut trajectory has non-finite series values")
        height = BLOCK[1]
        force, depth = s["wire_force"], s["wire_depth"]
        tail = slice(-c.tail_frames, None)
        peak = top_mean(force, c.peak_frames)
        inside = (depth > 0.1 * height) & (depth < 0.8 * height)
        mean_cut = float(force[inside].mean()) if inside.any() else float(force.mean())
        work = float(s["wire_work"][-1])
        contact = (depth > 0) & (depth <= c.contact_depth * height)
        if contact.any():
            k = float(np.sum(force[contact] * depth[contact]) / np.sum(depth[contact] ** 2))
        else:
            k = 0.0
        dmg = s["mean_damage"]
        final_damage = float(dmg[tail].mean())
        onset = first_crossing(depth, dmg, c.onset_level)
        if onset is None:  # never fractured that much: extrapolate smoothly from the final damage
            end = float(depth[-1])
            onset = end * min(3.0, c.onset_level / max(final_damage, c.onset_level / 3.0))
        moving = depth > 0.5 * height
        late = force[moving][-max(1, int(moving.sum() * 0.4)):] if moving.any() else force[tail]
        ratio = float(late.mean() / peak) if abs(peak) > 1e-12 else 0.0
        out = {
            "peak_force": peak,
            "mean_cut_force": mean_cut,
            "cut_work": float(np.log10(max(work, 1e-9))),
            "contact_stiffness": float(np.log10(max(k, 1e-3))),
            "fracture_onset_depth": float(onset),
            "final_mean_damage": final_damage,
            "damaged_fraction": float(s["damaged_fraction"][tail].mean()),
            "peak_column_drop": top_mean(s["column_drop"] - s["column_drop"][0], c.peak_frames),
            "resting_load": float(s["board_force"][:max(1, int(np.sum(depth < -0.25 * GAP)))].mean()),
            "settle_drop": float(-s["sag"][0]),
            "force_ratio": ratio,
            "damage_band_width": self._band_width(trajectory),
            "slice_drag_ratio": float(s["wire_drag"][inside].mean() / max(mean_cut, 1e-9)) if inside.any() else 0.0,
        }
        y = np.array([out[n] for n in FEATURE_NAMES], dtype=np.float64)
        if not np.all(np.isfinite(y)):
            raise TrajectoryError("cheese-cut features are not finite")
        return y

    @staticmethod
    def _band_width(trajectory: Trajectory) -> float:
        """Damage-weighted RMS distance (m) of the last frame's particles from the cut plane
        (x = ``centre_x``): how wide the broken band is (0 without damage)."""
        if trajectory.positions is None or trajectory.damage is None:
            return 0.0
        x = trajectory.positions[-1, :, 0].astype(np.float64) - float(trajectory.extra.get("centre_x", 0.0))
        d = trajectory.damage[-1].astype(np.float64)
        return float(np.sqrt(np.sum(d * x * x) / np.sum(d))) if d.sum() > 1e-9 else 0.0
