"""Trajectories beyond particles: named time series, the framework's trajectory file, frame caps."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from invphys.core.errors import InvphysError
from invphys.core.results import TimeSeries, Trajectory, frame_selection
from invphys.core.trajectory_io import load_trajectory, read_header, save_trajectory


def _series_only() -> Trajectory:
    t = np.linspace(0.0, 1.0, 11)
    traj = Trajectory(extra={"note": "lumped", "gains": np.arange(3.0), "opaque": object()})
    traj.add_series("force", t, np.sin(t), unit="N", description="force on the wall")
    traj.add_series("xyz", t[:5], np.ones((5, 3)), unit="m")
    return traj


def _particles(frames: int = 4, n: int = 6) -> Trajectory:
    rng = np.random.default_rng(0)
    traj = Trajectory(positions=rng.normal(size=(frames, n, 3)).astype(np.float32),
                      damage=np.zeros((frames, n), np.float32), labels=np.zeros(n, np.int8),
                      fields={"stress": np.ones((frames, n, 2))}, frame_indices=np.arange(frames) * 5, fps=10.0)
    traj.add_series("energy", np.arange(21) / 10.0, np.linspace(1, 0, 21), unit="J")
    return traj


def test_time_series_check_their_shapes() -> None:
    with pytest.raises(ValueError, match=r"must be \(T,\) or \(T, K\) with T = 3"):
        TimeSeries(times=[0, 1, 2], values=[1.0, 2.0])
    with pytest.raises(ValueError, match="non-decreasing"):
        TimeSeries(times=[0, 2, 1], values=[1.0, 2.0, 3.0])
    s = TimeSeries(times=[0.0, 1.0], values=[0.0, 10.0], unit="N")
    assert s.at(0.25) == pytest.approx(2.5) and len(s) == 2


def test_a_trajectory_needs_no_particles() -> None:
    traj = _series_only().check()
    assert not traj.has_particles and traj.n_frames == 0 and traj.n_particles == 0 and len(traj.times()) == 0
    assert traj.last_frame().series.keys() == traj.series.keys()
    with pytest.raises(ValueError, match="need particle positions"):
        Trajectory(damage=np.zeros((2, 2))).check()
    with pytest.raises(ValueError, match=r"damage must be \(4, 6\)"):
        Trajectory(positions=np.zeros((4, 6, 3)), damage=np.zeros((3, 6)), frame_indices=np.arange(4),
                   fps=1.0).check()
    with pytest.raises(ValueError, match="needs frame_indices and fps"):
        Trajectory(positions=np.zeros((4, 6, 3))).check()


def test_last_frame_keeps_series_whole_and_one_particle_frame() -> None:
    traj = _particles()
    last = traj.last_frame()
    assert last.n_frames == 1 and last.frame_indices.tolist() == [15]
    np.testing.assert_array_equal(last.positions[0], traj.positions[-1])
    assert last.fields["stress"].shape == (1, 6, 2)
    assert len(last.series["energy"]) == 21


def test_frame_selection_caps_and_ends_on_the_last_frame() -> None:
    assert frame_selection(5, 60).tolist() == [0, 1, 2, 3, 4]
    assert frame_selection(3363, 1).tolist() == [3362]
    sel = frame_selection(3363, 10)
    assert len(sel) == 10 and sel[0] == 0 and sel[-1] == 3362 and np.all(np.diff(sel) > 0)
    assert len(frame_selection(0, 5)) == 0


def test_trajectory_file_round_trips_series_particles_fields_and_extras(tmp_path) -> None:
    for traj in (_series_only(), _particles()):
        path = save_trajectory(traj, tmp_path / f"{traj.has_particles}.npz", simulator={"simulator": "x"})
        back = load_trajectory(path)
        assert list(back.series) == list(traj.series)
        for name, s in traj.series.items():
            np.testing.assert_array_equal(back.series[name].values, s.values)
            np.testing.assert_array_equal(back.series[name].times, s.times)
            assert back.series[name].unit == s.unit and back.series[name].description == s.description
        for key in ("positions", "damage", "labels", "frame_indices"):
            a, b = getattr(traj, key), getattr(back, key)
            assert (a is None and b is None) or np.array_equal(a, b)
        assert read_header(path)["simulator"] == {"simulator": "x"}
    back = load_trajectory(tmp_path / "False.npz")
    assert back.extra["note"] == "lumped" and back.extra["gains"].tolist() == [0.0, 1.0, 2.0]
    assert "opaque" not in back.extra  # neither an array nor JSON: documented as dropped
    np.testing.assert_array_equal(load_trajectory(tmp_path / "True.npz").fields["stress"], np.ones((4, 6, 2)))


def test_trajectory_file_errors_are_one_line(tmp_path) -> None:
    with pytest.raises(InvphysError, match="no trajectory at"):
        load_trajectory(tmp_path / "missing")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InvphysError, match="not a trajectory file"):
        load_trajectory(tmp_path / "bad.npz")
    np.savez(tmp_path / "future.npz", header=np.array(json.dumps({"format": "invphys.trajectory", "version": 99})))
    with pytest.raises(InvphysError, match="newer than this invphys reads"):
        load_trajectory(tmp_path / "future.npz")
    with pytest.raises(ValueError, match="positions must be"):
        save_trajectory(Trajectory(positions=np.zeros((2, 3)), frame_indices=[0, 1], fps=1.0), tmp_path / "x.npz")


def test_truncated_corrupt_and_inconsistent_files_are_one_line(tmp_path) -> None:
    """A truncated trajectory was an internal error (zipfile.BadZipFile) in `invphys render` and
    `invert --observed`; a file whose arrays disagree loaded and failed later."""
    from invphys.core.trajectory_io import TrajectoryFileError, load_with_header
    from invphys.core.user_targets import TargetError
    from invphys.inverter.target_input import load_trajectory as observed

    traj = Trajectory(positions=np.zeros((2, 3, 3)), damage=np.zeros((2, 3)), frame_indices=[0, 1], fps=1.0)
    data = save_trajectory(traj, tmp_path / "ok.npz").read_bytes()
    for cut in (len(data) - 1, len(data) // 2, 10):
        (tmp_path / "cut.npz").write_bytes(data[:cut])
        with pytest.raises(TrajectoryFileError, match=r"cut\.npz is not a trajectory file: truncated or corrupt"):
            load_trajectory(tmp_path / "cut.npz")
        with pytest.raises(TargetError, match=r"cannot read trajectory .*cut\.npz.*truncated or corrupt"):
            observed(tmp_path / "cut.npz")
    header = json.dumps({"format": "invphys.trajectory", "version": 1, "fps": 1.0, "series": [], "fields": []})
    np.savez(tmp_path / "odd.npz", header=np.array(header), positions=np.zeros((2, 3, 3)), damage=np.zeros((4, 4)),
             frame_indices=np.arange(2))
    with pytest.raises(TrajectoryFileError, match=r"damage must be \(2, 3\)"):
        load_trajectory(tmp_path / "odd.npz")
    for bad, needle in (("[1, 2]", "header is not a JSON object"), ('{"format": 1, "format": 2}', "appears twice"),
                        ('{"format": "invphys.trajectory", "series": 5, "fields": []}', "not a trajectory file")):
        np.savez(tmp_path / "h.npz", header=np.array(bad))
        with pytest.raises(TrajectoryFileError, match=needle):
            load_trajectory(tmp_path / "h.npz")
    os.mkfifo(tmp_path / "fifo.npz")
    with pytest.raises(TrajectoryFileError, match="not a regular file"):
        load_trajectory(tmp_path / "fifo.npz")
    back, head = load_with_header(tmp_path / "ok.npz")
    assert head["format"] == "invphys.trajectory" and back.n_frames == 2


def test_legacy_files_still_load(tmp_path) -> None:
    # the orange peel's own format before the framework had one, and the validate stage's old last frames
    pos = np.zeros((2, 3, 3), np.float32)
    np.savez(tmp_path / "old.npz", positions=pos, damage=np.zeros((2, 3)), labels=np.zeros(3, np.int8),
             frame_indices=np.array([0, 4]), fps=np.float64(24.0), extra_json=np.array('{"dx": 0.02}'),
             extra_gripper_path=np.ones((2, 3)))
    old = load_trajectory(tmp_path / "old.npz")
    assert old.n_frames == 2 and old.extra["dx"] == 0.02 and old.extra["gripper_path"].shape == (2, 3)
    np.savez(tmp_path / "frame.npz", positions=pos[0], damage=np.zeros(3), labels=np.zeros(3, np.int8), frame=7,
             fps=24.0)
    frame = load_trajectory(tmp_path / "frame.npz")
    assert frame.n_frames == 1 and frame.frame_indices.tolist() == [7]
