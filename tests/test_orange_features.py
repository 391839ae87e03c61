"""Orange-peel features on hand-built trajectories (exact values) and degenerate runs."""

from __future__ import annotations

import numpy as np
import pytest
from invphys_orange_peel.features import FEATURE_NAMES, OrangePeelFeatures, TrajectoryError

from invphys.core.results import Trajectory

EX = OrangePeelFeatures()


def _traj(positions, damage, labels, frames, fps=24.0, **extra) -> Trajectory:
    return Trajectory(positions=np.asarray(positions, np.float32), damage=np.asarray(damage, np.float32),
                      labels=np.asarray(labels, np.int8), frame_indices=np.asarray(frames), fps=fps,
                      extra=extra)


def _features(t: Trajectory) -> dict[str, float]:
    out = EX.extract(t)
    assert out.shape == (12,) and out.dtype == np.float64 and np.isfinite(out).all()
    return dict(zip(FEATURE_NAMES, out, strict=True))


def test_twelve_named_features() -> None:
    assert len(FEATURE_NAMES) == len(set(FEATURE_NAMES)) == 12
    assert EX.feature_names == FEATURE_NAMES


def test_exact_values_on_a_two_particle_story() -> None:
    """One skin particle lifts by 0.1 m per recorded frame (10 frames apart); one interior stays."""
    labels = [0, 1]
    frames = [0, 10, 20, 30]
    pos = [[[0, 0.1 * k, 0], [0, 0, 0]] for k in range(4)]
    dmg = [[0.0, 0.0], [0.2, 0.0], [0.6, 0.1], [0.9, 0.3]]
    f = _features(_traj(pos, dmg, labels, frames, fps=10.0, radius=0.15, dx=0.02))
    assert f["final_separation"] == pytest.approx(0.3)
    assert f["peak_separation_rate"] == pytest.approx(0.1 / 1.0)          # 0.1 m per 10 frames at 10 fps
    # fractured (d >= 0.5) fraction: 0, 0, 0.5, 0.5 -> onset at frame 20
    assert f["fracture_onset_frame"] == 20
    # rise 0, 0.1, 0.2, 0.3: half (0.15) reached halfway between frames 10 and 20
    assert f["separation_half_time"] == pytest.approx(15.0)
    assert f["skin_dispersion"] == 0.0 and f["interior_dispersion"] == 0.0
    # detachment threshold: initial distance 0 + dx/4 = 0.005 m; final distance 0.3 -> detached
    assert f["skin_detachment_fraction"] == 1.0
    assert f["interior_mean_displacement"] == 0.0 and f["interior_max_displacement"] == 0.0
    assert f["skin_mean_damage"] == pytest.approx(0.9) and f["interior_mean_damage"] == pytest.approx(0.3)
    assert f["skin_mean_displacement"] == pytest.approx(0.3)


def test_dispersion_and_displacement_statistics() -> None:
    rng = np.random.default_rng(0)
    n = 50
    labels = np.r_[np.zeros(n), np.ones(n)]
    first = rng.normal(size=(2 * n, 3))
    shift = rng.normal(size=(2 * n, 3)) * 0.1
    t = _traj([first, first + shift], np.zeros((2, 2 * n)), labels, [0, 10])
    f = _features(t)
    final = first + shift
    inner = final[n:]
    assert f["interior_dispersion"] == pytest.approx(
        np.sqrt(np.mean(np.sum((inner - inner.mean(0)) ** 2, 1))), rel=1e-5)
    disp = np.linalg.norm(shift, axis=1)
    assert f["interior_max_displacement"] == pytest.approx(disp[n:].max(), rel=1e-5)
    assert f["skin_mean_displacement"] == pytest.approx(disp[:n].mean(), rel=1e-5)


def test_degenerate_full_fracture_and_no_motion() -> None:
    pos = np.zeros((3, 4, 3))
    pos[:, :, 0] = [0.0, 0.1, 0.2, 0.3]
    full = _traj(pos, np.ones((3, 4)), [0, 0, 1, 1], [0, 5, 10])
    f = _features(full)
    assert f["fracture_onset_frame"] == 0              # fractured from the first frame
    assert f["separation_half_time"] == 10             # nothing separates: the last frame
    assert f["peak_separation_rate"] == 0.0
    assert f["skin_mean_damage"] == 1.0 == f["interior_mean_damage"]
    none = _traj(pos, np.zeros((3, 4)), [0, 0, 1, 1], [0, 5, 10])
    assert _features(none)["fracture_onset_frame"] == 15  # censored: last frame + stride


def test_single_frame_and_missing_region_are_defined() -> None:
    f = _features(_traj(np.zeros((1, 3, 3)), np.zeros((1, 3)), [0, 0, 0], [0]))
    assert f["interior_mean_displacement"] == 0.0 and f["skin_detachment_fraction"] == 0.0


def test_non_finite_trajectories_are_rejected() -> None:
    pos = np.zeros((2, 2, 3))
    pos[1, 0, 0] = np.nan
    with pytest.raises(TrajectoryError, match="non-finite"):
        EX.extract(_traj(pos, np.zeros((2, 2)), [0, 1], [0, 1]))
    with pytest.raises(TrajectoryError, match="shapes"):
        EX.extract(_traj(np.zeros((2, 2, 3)), np.zeros((3, 2)), [0, 1], [0, 1]))


def test_frame_stride_reads_every_nth_recorded_frame() -> None:
    pos = [[[0, 0.1 * k * k, 0], [0, 0, 0]] for k in range(5)]
    t = _traj(pos, np.zeros((5, 2)), [0, 1], [0, 10, 20, 30, 40])
    strided = OrangePeelFeatures(frame_stride=2).extract(t)
    assert strided[0] == pytest.approx(1.6)
    # rate from frames 0, 20, 40 only: (1.6 - 0.4) / (20 / 24)
    assert strided[1] == pytest.approx(1.2 / (20 / 24))
