"""Renders of orange-peel trajectories: PNG frames, a GIF (or MP4) animation and ParaView ``.ply`` files.

Colours follow the paper's Fig. 3: intact skin orange, intact flesh yellow, damaged skin purple,
damaged flesh cyan; a particle's colour blends from intact to damaged with its damage d in [0, 1].
Projection is orthographic from a fixed camera (azimuth/elevation in degrees), particles drawn back
to front.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.results import Trajectory, frame_selection

INTACT = np.array([[1.0, 0.55, 0.0], [1.0, 0.9, 0.15]])     # skin, flesh
DAMAGED = np.array([[0.5, 0.1, 0.65], [0.0, 0.8, 0.9]])     # skin, flesh


def particle_colours(labels: np.ndarray, damage: np.ndarray) -> np.ndarray:
    """(N, 3) RGB in [0, 1] for region labels (0 skin, 1 flesh) and damage values."""
    lab = np.clip(labels.astype(np.int64), 0, 1)
    d = np.clip(np.nan_to_num(damage.astype(np.float64)), 0.0, 1.0)[:, None]
    return (1.0 - d) * INTACT[lab] + d * DAMAGED[lab]


def project(points: np.ndarray, azim: float, elev: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthographic screen coordinates (u, v) and depth of (N, 3) points (y up)."""
    a, e = np.deg2rad(azim), np.deg2rad(elev)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    u = np.cos(a) * x - np.sin(a) * z
    w = np.sin(a) * x + np.cos(a) * z
    v = np.cos(e) * y - np.sin(e) * w
    depth = np.sin(e) * y + np.cos(e) * w
    return u, v, depth


def render_frame(points: np.ndarray, colours: np.ndarray, path: str | Path, *, azim: float = 60.0,
                 elev: float = 30.0, bounds: tuple[float, float, float, float] | None = None,
                 title: str = "", size: tuple[int, int] = (640, 480), extra_points: np.ndarray | None = None,
                 point_size: float | None = None, spacing: float | None = None) -> Path:
    """Draw one frame to a PNG and return its path.

    Markers are sized from the particle ``spacing`` (m) so that the surface reads as opaque; without
    it, from the median nearest-neighbour distance of ``points``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    u, v, depth = project(points, azim, elev)
    order = np.argsort(depth)  # far (small depth) first
    dpi = 100
    fig = plt.figure(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_facecolor((0.12, 0.12, 0.14))
    fig.patch.set_facecolor((0.12, 0.12, 0.14))
    if bounds is None:
        bounds = (u.min(), u.max(), v.min(), v.max())
    u0, u1, v0, v1 = bounds
    span = max(u1 - u0, (v1 - v0) * size[0] / size[1]) * 1.1
    cu, cv = (u0 + u1) / 2, (v0 + v1) / 2
    ax.set_xlim(cu - span / 2, cu + span / 2)
    ax.set_ylim(cv - span / 2 * size[1] / size[0], cv + span / 2 * size[1] / size[0])
    if point_size is None:
        if spacing is None:
            spacing = particle_spacing(points)
        px_per_m = size[0] / span
        diameter_pt = 0.9 * spacing * px_per_m * 72.0 / dpi
        point_size = float(np.clip(diameter_pt ** 2, 0.5, 400.0))
    ax.scatter(u[order], v[order], c=colours[order], s=point_size, linewidths=0)
    if extra_points is not None and len(extra_points):
        eu, ev, _ = project(np.atleast_2d(extra_points), azim, elev)
        ax.scatter(eu, ev, c="white", s=40, marker="x")
    ax.set_axis_off()
    if title:
        ax.text(0.02, 0.97, title, transform=ax.transAxes, color="white", va="top", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def particle_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance of (a sample of) ``points``."""
    from scipy.spatial import cKDTree

    pts = points[np.isfinite(points).all(axis=1)]
    if len(pts) < 2:
        return 1.0
    sample = pts[:: max(1, len(pts) // 2000)]
    d, _ = cKDTree(pts).query(sample, k=2)
    return float(np.median(d[:, 1]))


def write_ply(path: str | Path, points: np.ndarray, damage: np.ndarray, labels: np.ndarray) -> Path:
    """Binary little-endian PLY with x, y, z, damage, label per vertex (opens in ParaView)."""
    n = len(points)
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("damage", "<f4"), ("label", "u1")])
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    rec["damage"] = damage
    rec["label"] = labels.astype(np.uint8)
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
              "property float damage\nproperty uchar label\nend_header\n")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())
    return path


def render_trajectory(traj: Trajectory, out: str | Path, *, azim: float = 60.0, elev: float = 30.0,
                      animation: str = "gif", ply: bool = True, size: tuple[int, int] = (640, 480),
                      fps: float = 6.0, max_frames: int | None = None) -> dict[str, Any]:
    """Write ``frame_XXXX.png`` for every recorded frame (at most ``max_frames``, evenly spread, ending on
    the last), an animation and ``.ply`` files under ``out``.

    ``animation`` is ``"gif"``, ``"mp4"`` (needs imageio-ffmpeg) or ``"none"``. Returns the paths.
    """
    import imageio.v2 as imageio

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    all_pts = traj.positions.reshape(-1, 3)
    finite = np.isfinite(all_pts).all(axis=1)
    u, v, _ = project(all_pts[finite], azim, elev)
    bounds = (float(u.min()), float(u.max()), float(v.min()), float(v.max()))
    grip = traj.extra.get("gripper_path")
    dx = traj.extra.get("dx")
    spacing = float(dx) / 2 if dx is not None else particle_spacing(traj.positions[0])
    pngs, plys = [], []
    chosen = range(traj.n_frames) if max_frames is None else frame_selection(traj.n_frames, max_frames)
    for i in chosen:
        frame = traj.frame_indices[i]
        colours = particle_colours(traj.labels, traj.damage[i])
        title = f"frame {int(frame)}  t = {frame / traj.fps:.2f} s"
        g = None if grip is None or len(grip) != traj.n_frames else np.asarray(grip)[i][None]
        pngs.append(render_frame(traj.positions[i], colours, out / f"frame_{int(frame):04d}.png", azim=azim,
                                 elev=elev, bounds=bounds, title=title, size=size, extra_points=g,
                                 spacing=spacing))
        if ply:
            plys.append(write_ply(out / f"frame_{int(frame):04d}.ply", traj.positions[i], traj.damage[i],
                                  traj.labels))
    result: dict[str, Any] = {"frames": [str(p) for p in pngs], "ply": [str(p) for p in plys]}
    if animation != "none" and pngs:
        images = [imageio.imread(p) for p in pngs]
        if animation == "mp4":
            anim = out / "animation.mp4"
            imageio.mimsave(anim, images, fps=fps)
        else:
            anim = out / "animation.gif"
            imageio.mimsave(anim, images, duration=1.0 / fps, loop=0)
        result["animation"] = str(anim)
    return result
