"""Renders and trajectory files of the orange peel (no simulation: hand-made trajectories)."""

from __future__ import annotations

import numpy as np
import pytest
from invphys_orange_peel.render import particle_colours, project, render_trajectory, write_ply
from invphys_orange_peel.trajio import load_trajectory, save_trajectory

from invphys.core.errors import InvphysError
from invphys.core.results import Trajectory


def _traj(n: int = 200, frames: int = 3) -> Trajectory:
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(frames, n, 3)).astype(np.float32) * 0.05 + 0.3
    dmg = np.linspace(0, 1, frames * n, dtype=np.float32).reshape(frames, n)
    labels = (np.arange(n) % 2).astype(np.int8)
    return Trajectory(positions=pos, damage=dmg, labels=labels, frame_indices=np.arange(frames) * 10, fps=24.0,
                      extra={"dx": 0.02, "radius": 0.15, "gripper_path": pos[:, 0].copy(), "preset": "tiny"})


def test_fig3_colours() -> None:
    labels = np.array([0, 1, 0, 1], np.int8)
    c = particle_colours(labels, np.array([0.0, 0.0, 1.0, 1.0]))
    np.testing.assert_allclose(c[0], [1.0, 0.55, 0.0])    # intact skin: orange
    np.testing.assert_allclose(c[1], [1.0, 0.9, 0.15])    # intact flesh: yellow
    np.testing.assert_allclose(c[2], [0.5, 0.1, 0.65])    # damaged skin: purple
    np.testing.assert_allclose(c[3], [0.0, 0.8, 0.9])     # damaged flesh: cyan
    half = particle_colours(np.array([0], np.int8), np.array([0.5]))
    np.testing.assert_allclose(half[0], (c[0] + c[2]) / 2)


def test_orthographic_projection_keeps_lengths_in_the_image_plane() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    u, v, _ = project(pts, azim=0.0, elev=0.0)
    np.testing.assert_allclose([u[1] - u[0], v[2] - v[0]], [1.0, 1.0])
    u, v, depth = project(pts, azim=90.0, elev=0.0)
    assert abs(u[1] - u[0]) < 1e-12 and depth[1] - depth[0] == pytest.approx(1.0)  # x now points at the viewer


def test_trajectory_roundtrip_keeps_arrays_and_extras(tmp_path) -> None:
    t = _traj()
    path = save_trajectory(t, tmp_path / "run" / "trajectory.npz")
    back = load_trajectory(tmp_path / "run")
    np.testing.assert_array_equal(back.positions, t.positions)
    np.testing.assert_array_equal(back.damage, t.damage)
    np.testing.assert_array_equal(back.labels, t.labels)
    np.testing.assert_array_equal(back.frame_indices, t.frame_indices)
    assert back.fps == 24.0 and back.extra["dx"] == 0.02 and back.extra["preset"] == "tiny"
    np.testing.assert_array_equal(back.extra["gripper_path"], t.extra["gripper_path"])
    assert load_trajectory(path).n_particles == 200
    with pytest.raises(InvphysError, match="no trajectory"):
        load_trajectory(tmp_path / "missing")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InvphysError, match="not a trajectory file"):
        load_trajectory(tmp_path / "bad.npz")


def test_ply_is_binary_and_exact(tmp_path) -> None:
    t = _traj(n=5, frames=1)
    path = write_ply(tmp_path / "f.ply", t.positions[0], t.damage[0], t.labels)
    header, _, body = path.read_bytes().partition(b"end_header\n")
    assert header.startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")
    rec = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("damage", "<f4"), ("label", "u1")])
    np.testing.assert_array_equal(np.stack([rec["x"], rec["y"], rec["z"]], 1), t.positions[0])
    np.testing.assert_array_equal(rec["damage"], t.damage[0])
    np.testing.assert_array_equal(rec["label"], t.labels)


def test_render_trajectory_writes_frames_animation_and_ply(tmp_path) -> None:
    out = render_trajectory(_traj(), tmp_path / "r", size=(160, 120))
    assert [p.rsplit("/", 1)[1] for p in out["frames"]] == ["frame_0000.png", "frame_0010.png", "frame_0020.png"]
    assert len(out["ply"]) == 3 and out["animation"].endswith("animation.gif")
    import imageio.v2 as imageio

    gif = imageio.mimread(out["animation"])
    assert len(gif) == 3 and gif[0].shape[:2] == (120, 160)
