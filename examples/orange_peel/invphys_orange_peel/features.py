"""The 12 behavioural features of an orange-peel run (paper sec. 3.2; exact definitions and formulas in
docs/orange-peel/features.md).

Every feature is a smooth functional of the run: series measured every frame on the device (skin-interior
centroid distance, mean damage, gripper work; ``Trajectory.extra``) are read at frame resolution with
interpolated threshold crossings, and end-of-run statistics are averaged over the recorded frames of the
last ``tail_seconds``. Notation: recorded frames k with frame indices f_k; S = skin particles (label 0),
I = interior particles (label 1); x_p(0) is the settled state (frame 0).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import FeatureExtractor, PluginConfig
from invphys.core.results import Trajectory

#: feature name -> unit (docs/orange-peel/features.md); "" for a fraction or a damage in [0, 1]
FEATURE_UNITS: dict[str, str] = {
    "final_separation": "log10 m",         # separation gained over the built scene's (0.3.0)
    "peak_separation_rate": "log10 m/s",   # (0.3.0)
    "fracture_onset_frame": "frame",       # real-valued frame index
    "separation_half_time": "frame",       # real-valued frame index
    "skin_dispersion": "m",
    "skin_detachment_fraction": "",
    "interior_mean_displacement": "log10 m",   # (0.3.0)
    "interior_max_displacement": "log10 m",    # robust top statistic away from the gripper (0.3.0)
    "interior_dispersion": "m",
    "skin_mean_damage": "",
    "interior_mean_damage": "",
    "peeling_work": "log10 J",             # our 12th feature
}
FEATURE_NAMES: tuple[str, ...] = tuple(FEATURE_UNITS)

#: the floor of the gripper work before the logarithm (J)
WORK_FLOOR = 1e-9
#: the features reported in log10 units since simulator 0.3.0 -> the offset added before the logarithm (a
#: guard far below every measured value, so that a run that does not move stays finite); final_separation
#: is the log of the separation *gained* over the built scene's (m), the others of the plain statistic
LOG_OFFSETS: dict[str, float] = {
    "final_separation": 1e-4,
    "peak_separation_rate": 1e-5,
    "interior_mean_displacement": 1e-6,
    "interior_max_displacement": 1e-6,
}


class TrajectoryError(InvphysError, ValueError):
    """A trajectory that cannot be summarised (non-finite values, wrong shapes, missing series)."""


# -- small named statistics (each documented in features.md) ---------------------------------------

def centroid(x: np.ndarray) -> np.ndarray:
    return x.mean(axis=0) if len(x) else np.zeros(3)


def dispersion(x: np.ndarray) -> float:
    """Root-mean-square distance of the points from their centroid (0 when empty)."""
    if len(x) == 0:
        return 0.0
    return float(np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=1))))


def top_mean(values: np.ndarray, fraction: float) -> float:
    """Mean of the largest ``ceil(fraction * n)`` values (0 when empty): a robust maximum."""
    if values.size == 0:
        return 0.0
    k = max(1, int(np.ceil(fraction * values.size)))
    return float(np.mean(np.partition(values, values.size - k)[values.size - k:]))


def first_crossing(series: np.ndarray, level: float) -> float | None:
    """The real-valued index at which ``series`` first reaches ``level`` (linear interpolation), or None."""
    hit = np.flatnonzero(series >= level)
    if len(hit) == 0:
        return None
    k = int(hit[0])
    if k == 0:
        return 0.0
    a, b = float(series[k - 1]), float(series[k])
    return k - 1 + ((level - a) / (b - a) if b > a else 1.0)


def onset_index(mean_damage: np.ndarray, level: float) -> float:
    """Fracture onset (frame): the interpolated crossing of ``level`` by the mean damage; a run that
    never gets there is extrapolated smoothly from its final mean damage D_F:
    ``F (1 + min(1, ln(level / D_F)))`` (equal to F at D_F = level, 2F for no damage)."""
    hit = first_crossing(mean_damage, level)
    if hit is not None:
        return hit
    last = len(mean_damage) - 1
    dfinal = max(float(mean_damage[-1]), 1e-30)
    return last * (1.0 + min(1.0, float(np.log(level / dfinal))))


def windowed_peak_rate(series: np.ndarray, fps: float, window: int) -> float:
    """max(0, max_f (s(f + w) - s(f)) / (w / fps)) over every frame f: a peak rate that is continuous in
    the series (every frame is used, the window smooths frame-to-frame vibration)."""
    w = int(min(max(1, window), len(series) - 1))
    if w < 1:
        return 0.0
    rates = (series[w:] - series[:-w]) * (fps / w)
    return float(max(rates.max(), 0.0))


def half_time(separation: np.ndarray, final: float, radius: float) -> float:
    """The interpolated frame at which sep - sep(0) first reaches half of (final - sep(0)); the last
    frame when the centroids separate by no more than 1e-3 R."""
    rise = separation - separation[0]
    target = final - separation[0]
    if target <= 1e-3 * radius:
        return float(len(separation) - 1)
    hit = first_crossing(rise, 0.5 * target)
    return float(len(separation) - 1) if hit is None else hit


class SoftDetachment:
    """``soft_detached`` for one run: the threshold comes from the first frame, computed once here and applied
    to each tail frame by calling the object (the search stops at tau + w: farther particles count 1)."""

    def __init__(self, first: np.ndarray, skin: np.ndarray, inner: np.ndarray, dx: float | None) -> None:
        self.skin, self.inner = skin, inner
        self.empty = not skin.any() or not inner.any()
        if self.empty:
            return
        from scipy.spatial import cKDTree

        d0, _ = cKDTree(first[inner], balanced_tree=False, compact_nodes=False).query(first[skin])
        scale = float(dx) if dx is not None else float(d0.max())
        self.tau, self.width = float(d0.max()) + 0.25 * scale, max(0.5 * scale, 1e-12)

    def __call__(self, final: np.ndarray) -> float:
        if self.empty:
            return 0.0
        from scipy.spatial import cKDTree

        tree = cKDTree(final[self.inner], balanced_tree=False, compact_nodes=False)  # faster to build, same distances
        d1, _ = tree.query(final[self.skin], distance_upper_bound=self.tau + self.width)  # inf past the bound
        s = np.clip((d1 - self.tau) / self.width, 0.0, 1.0)
        return float(np.mean(s * s * (3.0 - 2.0 * s)))


def soft_detached(first: np.ndarray, final: np.ndarray, skin: np.ndarray, inner: np.ndarray,
                  dx: float | None) -> float:
    """Soft fraction of skin particles away from all flesh: mean of smoothstep((d1 - tau) / w) with d1
    a skin particle's distance to the nearest interior particle, tau = max initial d + dx/4, w = dx/2."""
    return SoftDetachment(first, skin, inner, dx)(final)


def away_from_gripper(first: np.ndarray, inner: np.ndarray, gripped: np.ndarray | None,
                      cells: float, dx: float | None) -> np.ndarray:
    """Interior mask without the particles within ``cells * dx`` of a gripped particle at frame 0."""
    if gripped is None or dx is None or not np.any(gripped) or cells <= 0:
        return inner
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(first[np.asarray(gripped, bool)]).query(first)
    return inner & (dist > cells * float(dx))


def log_units(linear: np.ndarray, separation_baseline: float) -> np.ndarray:
    """The reported features from the same statistics in linear units (the units simulator 0.2.0 stored:
    final_separation and the displacements in m, the rate in m/s; ``peeling_work`` is already log10 J):
    each feature of :data:`LOG_OFFSETS` becomes ``log10(v + offset)``, with final_separation's ``v`` the
    separation gained over ``separation_baseline`` (clipped at 0)."""
    out = np.array(linear, dtype=np.float64, copy=True)
    for name, offset in LOG_OFFSETS.items():
        k = FEATURE_NAMES.index(name)
        v = max(out[k] - separation_baseline, 0.0) if name == "final_separation" else out[k]
        out[k] = np.log10(v + offset)
    return out


class OrangePeelFeatures(FeatureExtractor):
    """The paper's 11 named features plus the gripper's peeling work, from an orange-peel trajectory.

    Reads the per-frame series ``frame_separation``, ``frame_mean_damage`` and ``frame_work`` from
    ``Trajectory.extra`` (the simulator records them every frame); without them separation and mean damage
    are taken from the recorded frames, and ``peeling_work`` needs ``frame_work``. Degenerate runs are
    defined, never NaN (docs/orange-peel/features.md).
    """

    name: ClassVar[str] = "orange_peel_features"

    class Config(PluginConfig):
        """Settings of the orange-peel feature extractor."""

        tail_seconds: float = Field(1.0, ge=0, description="end-of-run statistics: mean over the recorded "
                                                           "frames of the last this many seconds")
        onset_mean_damage: float = Field(0.005, gt=0, lt=1,
                                         description="fracture onset: the mean damage of all particles "
                                                     "reaches this")
        rate_window_seconds: float = Field(0.5, gt=0, description="separation-rate window (s)")
        top_fraction: float = Field(0.01, gt=0, le=1, description="interior_max_displacement: mean of the "
                                                                   "top this fraction")
        gripper_exclusion_cells: float = Field(2.0, ge=0, description="interior_max_displacement ignores "
                                                                      "particles this close to the gripped "
                                                                      "patch (cells)")

    @property
    def feature_names(self) -> tuple[str, ...]:
        return FEATURE_NAMES

    @property
    def feature_units(self) -> tuple[str, ...]:
        return tuple(FEATURE_UNITS.values())

    def extract(self, trajectory: Trajectory) -> np.ndarray:
        """Features (12,) float64 of one trajectory, all finite."""
        t = trajectory
        pos, dmg, frames, labels = self._arrays(t)
        fps = float(t.fps)
        skin, inner = labels == 0, labels == 1
        radius = float(t.extra.get("radius", np.ptp(pos[0][:, 0]) / 2 or 1.0))
        dx = t.extra.get("dx")
        dx = float(dx) if dx is not None else None
        sep, mean_d, series_fps = self._series(t, pos, dmg, skin, inner, frames, fps)
        work = self._work(t)

        times = frames / fps
        tail = times >= times[-1] - self.config.tail_seconds - 1e-9
        tail_series = np.arange(len(sep)) / series_fps >= (len(sep) - 1) / series_fps \
            - self.config.tail_seconds - 1e-9
        final_sep = float(sep[tail_series].mean())
        peak = windowed_peak_rate(sep, series_fps, round(self.config.rate_window_seconds * series_fps))
        to_frames = fps / series_fps  # series index -> frame index (1 when the series is per frame)
        onset = onset_index(mean_d, self.config.onset_mean_damage) * to_frames
        half = half_time(sep, final_sep, radius) * to_frames

        first = pos[0]
        far = away_from_gripper(first, inner, t.extra.get("gripped"), self.config.gripper_exclusion_cells, dx)
        detached = SoftDetachment(first, skin, inner, dx)
        rows = []
        for k in np.flatnonzero(tail):
            x, d = pos[k], dmg[k]
            disp = np.linalg.norm(x - first, axis=1)
            rows.append([
                dispersion(x[skin]), detached(x),
                _mean(disp[inner]), top_mean(disp[far], self.config.top_fraction), dispersion(x[inner]),
                _mean(d[skin]), _mean(d[inner]),
            ])
        ends = np.mean(np.asarray(rows, np.float64), axis=0)
        linear = np.array([final_sep, peak, onset, half, *ends, np.log10(max(work, WORK_FLOOR))], dtype=np.float64)
        out = log_units(linear, self._baseline(t, sep))
        if not np.isfinite(out).all():  # pragma: no cover - guarded above; never return NaN silently
            raise TrajectoryError(f"non-finite features {dict(zip(FEATURE_NAMES, out, strict=True))}")
        return out

    # -- inputs ----------------------------------------------------------------------------------
    @staticmethod
    def _arrays(t: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        pos = np.asarray(t.positions, dtype=np.float64)
        dmg = np.asarray(t.damage, dtype=np.float64)
        frames = np.asarray(t.frame_indices, dtype=np.float64)
        if pos.ndim != 3 or pos.shape[2] != 3 or dmg.shape != pos.shape[:2] or len(frames) != len(pos):
            raise TrajectoryError(f"inconsistent trajectory shapes: positions {pos.shape}, damage {dmg.shape}, "
                                  f"frames {frames.shape}")
        if len(pos) == 0:
            raise TrajectoryError("a trajectory needs at least one recorded frame")
        if not (np.isfinite(pos).all() and np.isfinite(dmg).all()):
            raise TrajectoryError("trajectory contains non-finite positions or damage; failed runs carry no "
                                  "trajectory and have no features")
        return pos, dmg, frames, np.asarray(t.labels)

    @staticmethod
    def _series(t: Trajectory, pos: np.ndarray, dmg: np.ndarray, skin: np.ndarray, inner: np.ndarray,
                frames: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(separation, mean damage, series rate in 1/s): every frame when the simulator recorded them,
        else from the recorded frames (then uniformly spaced recorded frames are required)."""
        sep = t.extra.get("frame_separation")
        mean_d = t.extra.get("frame_mean_damage")
        if sep is not None and mean_d is not None:
            sep, mean_d = np.asarray(sep, np.float64), np.asarray(mean_d, np.float64)
            if sep.shape != mean_d.shape or len(sep) != int(frames[-1]) + 1:
                raise TrajectoryError(f"per-frame series of length {len(sep)}/{len(mean_d)} do not match the "
                                      f"last recorded frame {int(frames[-1])}")
            if not (np.isfinite(sep).all() and np.isfinite(mean_d).all()):
                raise TrajectoryError("non-finite per-frame series")
            return sep, mean_d, fps
        steps = np.diff(frames)
        if len(steps) and not np.allclose(steps, steps[0]):
            raise TrajectoryError("without per-frame series the recorded frames must be evenly spaced")
        stride = float(steps[0]) if len(steps) else 1.0
        sep = np.array([np.linalg.norm(centroid(p[skin]) - centroid(p[inner])) for p in pos])
        return sep, dmg.mean(axis=1), fps / stride

    @staticmethod
    def _baseline(t: Trajectory, sep: np.ndarray) -> float:
        """The separation ``final_separation`` counts from: the built scene's skin-interior centroid distance
        (``extra['scene_separation']``, the same for every run of a preset), else the first frame's."""
        base = t.extra.get("scene_separation")
        if base is None:
            return float(sep[0])
        base = float(base)
        if not np.isfinite(base):
            raise TrajectoryError(f"non-finite scene_separation {base}")
        return base

    @staticmethod
    def _work(t: Trajectory) -> float:
        work = t.extra.get("frame_work")
        if work is None:
            raise TrajectoryError("peeling_work needs the per-frame gripper work 'frame_work' in the trajectory's "
                                  "extra (recorded by the orange-peel simulator)")
        work = np.asarray(work, np.float64)
        if work.size == 0 or not np.isfinite(work).all():
            raise TrajectoryError("non-finite or empty gripper work series")
        return float(work[-1])


def _mean(a: np.ndarray) -> float:
    return float(a.mean()) if a.size else 0.0
