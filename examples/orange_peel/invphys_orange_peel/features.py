"""The 12 behavioural features of an orange-peel run (paper sec. 3.2; exact definitions in
docs/orange-peel/features.md).

Notation: recorded frames k = 0..K-1 with frame indices f_k and times t_k; S = skin particles
(label 0), I = interior particles (label 1); c_S(k), c_I(k) their centroids; sep(k) = |c_S(k) - c_I(k)|.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import FeatureExtractor, PluginConfig
from invphys.core.results import Trajectory

FEATURE_NAMES: tuple[str, ...] = (
    "final_separation",            # m
    "peak_separation_rate",        # m/s
    "fracture_onset_frame",        # frame index
    "separation_half_time",        # frame index
    "skin_dispersion",             # m
    "skin_detachment_fraction",    # [0, 1]
    "interior_mean_displacement",  # m
    "interior_max_displacement",   # m
    "interior_dispersion",         # m
    "skin_mean_damage",            # [0, 1]
    "interior_mean_damage",        # [0, 1]
    "skin_mean_displacement",      # m (our 12th feature)
)


class TrajectoryError(InvphysError, ValueError):
    """A trajectory that cannot be summarised (non-finite values, wrong shapes)."""


def _centroid(x: np.ndarray) -> np.ndarray:
    return x.mean(axis=0) if len(x) else np.zeros(3)


def _dispersion(x: np.ndarray) -> float:
    if len(x) == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=1))))


class OrangePeelFeatures(FeatureExtractor):
    """The paper's 11 named features plus skin mean displacement, from an orange-peel trajectory.

    Degenerate runs are defined, not NaN: a run that never fractures gets
    ``fracture_onset_frame = last frame + stride`` (stride = first recording interval); a run whose skin and
    interior centroids do not separate by more than ``1e-3 * radius`` gets
    ``separation_half_time = last frame``; an empty region contributes zeros.
    """

    name: ClassVar[str] = "orange_peel_features"

    class Config(PluginConfig):
        """Settings of the orange-peel feature extractor."""

        frame_stride: int = Field(1, ge=1, description="use every n-th recorded frame (plus the last)")
        onset_damage: float = Field(0.5, gt=0, le=1, description="a particle counts as fractured at d >= this")
        onset_fraction: float = Field(0.005, gt=0, lt=1,
                                      description="fracture onset: fraction of fractured particles reached")

    @property
    def feature_names(self) -> tuple[str, ...]:
        return FEATURE_NAMES

    def extract(self, trajectory: Trajectory) -> np.ndarray:
        """Features (12,) float64 of one trajectory, all finite."""
        t = trajectory
        pos = np.asarray(t.positions, dtype=np.float64)
        dmg = np.asarray(t.damage, dtype=np.float64)
        frames = np.asarray(t.frame_indices, dtype=np.float64)
        labels = np.asarray(t.labels)
        if pos.ndim != 3 or pos.shape[2] != 3 or dmg.shape != pos.shape[:2] or len(frames) != len(pos):
            raise TrajectoryError(f"inconsistent trajectory shapes: positions {pos.shape}, damage {dmg.shape}, "
                                  f"frames {frames.shape}")
        if len(pos) == 0:
            raise TrajectoryError("a trajectory needs at least one recorded frame")
        if not (np.isfinite(pos).all() and np.isfinite(dmg).all()):
            raise TrajectoryError("trajectory contains non-finite positions or damage; failed runs carry no "
                                  "trajectory and have no features")
        sel = np.arange(0, len(pos), self.config.frame_stride)
        if sel[-1] != len(pos) - 1:
            sel = np.append(sel, len(pos) - 1)
        pos, dmg, frames = pos[sel], dmg[sel], frames[sel]
        times = frames / float(t.fps)
        skin, inner = labels == 0, labels == 1
        radius = float(t.extra.get("radius", np.ptp(pos[0][:, 0]) / 2 or 1.0))

        sep = np.array([np.linalg.norm(_centroid(p[skin]) - _centroid(p[inner])) for p in pos])
        final_sep = float(sep[-1])
        if len(sep) > 1:
            rates = np.diff(sep) / np.maximum(np.diff(times), 1e-12)
            peak_rate = float(max(rates.max(), 0.0))
        else:
            peak_rate = 0.0

        stride = float(frames[1] - frames[0]) if len(frames) > 1 else 1.0
        fractured = (dmg >= self.config.onset_damage).mean(axis=1)
        hit = np.flatnonzero(fractured >= self.config.onset_fraction)
        onset = float(frames[hit[0]]) if len(hit) else float(frames[-1] + stride)

        rise = sep - sep[0]
        if rise[-1] <= 1e-3 * radius:
            half = float(frames[-1])
        else:
            k = int(np.flatnonzero(rise >= 0.5 * rise[-1])[0])
            if k == 0:
                half = float(frames[0])
            else:
                a, b = rise[k - 1], rise[k]
                frac = (0.5 * rise[-1] - a) / (b - a) if b > a else 1.0
                half = float(frames[k - 1] + frac * (frames[k] - frames[k - 1]))

        final, first = pos[-1], pos[0]
        disp = np.linalg.norm(final - first, axis=1)
        detach = self._detachment(first, final, skin, inner, t)

        def mean(a: np.ndarray) -> float:
            return float(a.mean()) if a.size else 0.0

        out = np.array([
            final_sep, peak_rate, onset, half,
            _dispersion(final[skin]), detach,
            mean(disp[inner]), float(disp[inner].max()) if inner.any() else 0.0, _dispersion(final[inner]),
            mean(dmg[-1][skin]), mean(dmg[-1][inner]), mean(disp[skin]),
        ], dtype=np.float64)
        if not np.isfinite(out).all():  # pragma: no cover - guarded above; never return NaN silently
            raise TrajectoryError(f"non-finite features {dict(zip(FEATURE_NAMES, out, strict=True))}")
        return out

    @staticmethod
    def _detachment(first: np.ndarray, final: np.ndarray, skin: np.ndarray, inner: np.ndarray,
                    t: Trajectory) -> float:
        """Fraction of skin particles farther from every interior particle than any skin particle was
        at the start, plus half a particle spacing."""
        if not skin.any() or not inner.any():
            return 0.0
        from scipy.spatial import cKDTree

        d0, _ = cKDTree(first[inner]).query(first[skin])
        dx = t.extra.get("dx")
        margin = 0.5 * float(dx) / 2 if dx is not None else 0.25 * float(d0.max())
        threshold = float(d0.max()) + margin
        d1, _ = cKDTree(final[inner]).query(final[skin])
        return float(np.mean(d1 > threshold))
