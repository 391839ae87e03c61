"""Orange-peel features on hand-built trajectories (exact values), smoothness and degenerate runs."""

from __future__ import annotations

import numpy as np
import pytest
from invphys_orange_peel.features import (
    FEATURE_NAMES,
    LOG_OFFSETS,
    OrangePeelFeatures,
    TrajectoryError,
    first_crossing,
    onset_index,
    soft_detached,
    top_mean,
    windowed_peak_rate,
)

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


def test_twelve_named_features_keep_the_papers_eleven() -> None:
    assert len(FEATURE_NAMES) == len(set(FEATURE_NAMES)) == 12
    assert EX.feature_names == FEATURE_NAMES
    assert FEATURE_NAMES[-1] == "peeling_work" and "skin_mean_displacement" not in FEATURE_NAMES


def test_exact_values_on_a_two_particle_story() -> None:
    """One skin particle lifts 0.01 m per frame for 30 frames at 10 fps; one interior stays put.

    Series every frame: sep(f) = 0.01 f; mean damage 0.001 f; the gripper's work grows to 2 J. Four features
    are log10 of the statistic plus a small guard offset (``LOG_OFFSETS``); without ``scene_separation`` the
    separation gain counts from sep(0) = 0.
    """
    labels = [0, 1]
    frames = [0, 10, 20, 30]
    pos = [[[0, 0.1 * k, 0], [0, 0, 0]] for k in range(4)]
    dmg = [[0.0, 0.0], [0.2, 0.0], [0.6, 0.1], [0.9, 0.3]]
    f31 = np.arange(31.0)
    t = _traj(pos, dmg, labels, frames, fps=10.0, radius=0.15, dx=0.02, frame_separation=0.01 * f31,
              frame_mean_damage=0.001 * f31, frame_work=2.0 * f31 / 30)
    f = _features(t)
    # tail: the last second = frames 20..30 of the series (mean 0.25) and recorded frames 20, 30
    assert f["final_separation"] == pytest.approx(np.log10(0.25 + 1e-4))
    assert f["peak_separation_rate"] == pytest.approx(np.log10(0.1 + 1e-5))  # 0.01 m per frame at 10 fps
    assert f["fracture_onset_frame"] == pytest.approx(5.0)              # mean damage reaches 0.005 at f = 5
    assert f["separation_half_time"] == pytest.approx(12.5)             # rise reaches 0.125 at f = 12.5
    assert f["skin_dispersion"] == 0.0 and f["interior_dispersion"] == 0.0
    # detachment: tau = 0 + dx/4 = 0.005, width dx/2 = 0.01; distances 0.2 and 0.3 are far past it
    assert f["skin_detachment_fraction"] == 1.0
    assert f["interior_mean_displacement"] == pytest.approx(-6.0) == f["interior_max_displacement"]  # the guard
    assert f["skin_mean_damage"] == pytest.approx(0.75) and f["interior_mean_damage"] == pytest.approx(0.2)
    assert f["peeling_work"] == pytest.approx(np.log10(2.0))
    # the simulator's built-scene separation is the baseline of the gain: 0.25 - 0.05 m
    g = _features(_traj(pos, dmg, labels, frames, fps=10.0, radius=0.15, dx=0.02, frame_separation=0.01 * f31,
                        frame_mean_damage=0.001 * f31, frame_work=2.0 * f31 / 30, scene_separation=0.05))
    assert g["final_separation"] == pytest.approx(np.log10(0.20 + 1e-4))
    assert g["separation_half_time"] == f["separation_half_time"]    # counts from sep(0), not the scene
    assert set(LOG_OFFSETS) == {n for n, u in zip(FEATURE_NAMES, EX.feature_units, strict=True)
                                if u.startswith("log10") and n != "peeling_work"}


def test_robust_top_statistic_and_gripper_exclusion() -> None:
    """interior_max_displacement: mean of the top 1 % away from the gripped patch, not the maximum."""
    n = 400
    labels = np.r_[np.zeros(1), np.ones(n)]
    first = np.zeros((n + 1, 3))
    first[:, 0] = np.r_[0.0, np.linspace(0.0, 1.0, n)]  # the skin particle (gripped) sits at x = 0
    final = first.copy()
    final[1:, 1] = np.linspace(0.0, 0.2, n)[::-1]        # interior next to the gripper moves the most
    gripped = np.r_[True, np.zeros(n, bool)]
    series = {"frame_separation": np.zeros(11), "frame_mean_damage": np.zeros(11), "frame_work": np.ones(11)}
    t = _traj([first, final], np.zeros((2, n + 1)), labels, [0, 10], fps=1.0, dx=0.1, gripped=gripped, **series)
    f = _features(t)
    disp = np.linspace(0.0, 0.2, n)[::-1]
    far = first[1:, 0] > 0.2                               # 2 cells of 0.1 m from the gripped particle
    expect = np.sort(disp[far])[-int(np.ceil(0.01 * far.sum())):].mean()
    assert f["interior_max_displacement"] == pytest.approx(np.log10(expect + 1e-6), rel=1e-5)
    assert 10 ** f["interior_max_displacement"] < disp.max() - 0.01
    assert top_mean(np.arange(200.0), 0.01) == pytest.approx(198.5)


def test_soft_detachment_matches_a_brute_force_count() -> None:
    """The bounded KD-tree search gives the brute-force smoothstep count: particles in the band count in
    part, those past tau + w (the search bound) fully, those near the flesh not at all."""
    rng = np.random.default_rng(3)
    g = np.linspace(0.0, 1.0, 11)
    flesh = np.stack(np.meshgrid(g, g, g[:6], indexing="ij"), -1).reshape(-1, 3)      # a slab up to z = 0.5
    peel = np.c_[rng.uniform(size=(200, 2)), np.full(200, 0.52)]                     # a skin layer above it
    first = np.vstack([peel, flesh])
    skin, inner = np.r_[np.ones(200, bool), np.zeros(len(flesh), bool)], np.r_[np.zeros(200, bool), np.ones(len(flesh), bool)]
    for dx in (0.05, 0.1, None):
        final = first + rng.normal(scale=0.003, size=first.shape)
        final[:200, 2] += rng.uniform(0.0, 0.2, size=200)                             # lifted by 0 to 0.2

        def nearest(x: np.ndarray) -> np.ndarray:
            return np.sqrt(((x[skin][:, None, :] - x[inner][None, :, :]) ** 2).sum(-1)).min(axis=1)

        d0, d1 = nearest(first), nearest(final)
        scale = dx if dx is not None else d0.max()
        tau, width = d0.max() + 0.25 * scale, 0.5 * scale
        u = np.clip((d1 - tau) / width, 0.0, 1.0)
        assert (u == 0).any() and (u == 1).any() and ((u > 0) & (u < 1)).any()  # every regime is exercised
        assert soft_detached(first, final, skin, inner, dx) == pytest.approx(np.mean(u * u * (3 - 2 * u)), rel=1e-12)


def test_onset_is_continuous_and_extrapolates_runs_that_never_fracture() -> None:
    d = np.array([0.0, 0.002, 0.004, 0.006, 0.008])
    assert onset_index(d, 0.005) == pytest.approx(2.5)
    assert first_crossing(d, 0.0) == 0.0 and first_crossing(d, 1.0) is None
    # never reaching the level: F (1 + min(1, ln(level / D_F))), continuous at D_F = level
    assert onset_index(np.array([0.0, 0.005 * 0.999]), 0.005) == pytest.approx(1.0, abs=2e-3)
    assert onset_index(np.zeros(11), 0.005) == 20.0
    # a small change of the series moves the onset a little, not by a recording stride
    assert abs(onset_index(d * 1.01, 0.005) - onset_index(d, 0.005)) < 0.05


def test_windowed_rate_uses_every_frame() -> None:
    s = np.r_[np.zeros(10), np.linspace(0, 1, 11), np.ones(10)]  # +0.1 per frame during 10 frames
    assert windowed_peak_rate(s, 10.0, 5) == pytest.approx(1.0)
    assert windowed_peak_rate(s[::-1], 10.0, 5) == 0.0


def test_degenerate_full_fracture_and_no_motion() -> None:
    pos = np.zeros((3, 4, 3))
    pos[:, :, 0] = [0.0, 0.1, 0.2, 0.3]
    series = {"frame_separation": np.full(11, 0.05), "frame_work": np.zeros(11)}
    full = _traj(pos, np.ones((3, 4)), [0, 0, 1, 1], [0, 5, 10], frame_mean_damage=np.ones(11), **series)
    f = _features(full)
    assert f["fracture_onset_frame"] == 0              # fractured from the first frame
    assert f["separation_half_time"] == 10             # nothing separates: the last frame
    assert f["peak_separation_rate"] == pytest.approx(-5.0)  # no rise: log10 of the 1e-5 m/s guard
    assert f["skin_mean_damage"] == 1.0 == f["interior_mean_damage"]
    assert f["peeling_work"] == -9.0                   # no work: the floor, 1e-9 J
    none = _traj(pos, np.zeros((3, 4)), [0, 0, 1, 1], [0, 5, 10], frame_mean_damage=np.zeros(11), **series)
    assert _features(none)["fracture_onset_frame"] == 20  # never: twice the run


def test_recorded_frames_stand_in_for_missing_series_except_work() -> None:
    pos = [[[0, 0.1 * k, 0], [0, 0, 0]] for k in range(3)]
    t = _traj(pos, np.zeros((3, 2)), [0, 1], [0, 10, 20], fps=10.0, frame_work=np.linspace(0, 1, 21))
    f = _features(t)
    assert f["final_separation"] == pytest.approx(np.log10(0.15 + 1e-4))  # recorded frames 10, 20: the last second
    assert f["separation_half_time"] == pytest.approx(7.5)
    with pytest.raises(TrajectoryError, match="frame_work"):
        EX.extract(_traj(pos, np.zeros((3, 2)), [0, 1], [0, 10, 20]))


def test_single_frame_and_missing_region_are_defined() -> None:
    f = _features(_traj(np.zeros((1, 3, 3)), np.zeros((1, 3)), [0, 0, 0], [0], frame_work=np.zeros(1)))
    assert f["interior_mean_displacement"] == pytest.approx(-6.0) and f["skin_detachment_fraction"] == 0.0


def test_non_finite_and_inconsistent_trajectories_are_rejected() -> None:
    pos = np.zeros((2, 2, 3))
    pos[1, 0, 0] = np.nan
    with pytest.raises(TrajectoryError, match="non-finite"):
        EX.extract(_traj(pos, np.zeros((2, 2)), [0, 1], [0, 1], frame_work=np.zeros(2)))
    with pytest.raises(TrajectoryError, match="do not match"):
        EX.extract(_traj(np.zeros((2, 2, 3)), np.zeros((2, 2)), [0, 1], [0, 5], frame_separation=np.zeros(3),
                         frame_mean_damage=np.zeros(3), frame_work=np.zeros(6)))
    with pytest.raises(TrajectoryError, match="non-finite"):
        EX.extract(_traj(np.zeros((2, 2, 3)), np.zeros((2, 2)), [0, 1], [0, 1], frame_work=[0.0, np.nan]))
