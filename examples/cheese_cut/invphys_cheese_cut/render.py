"""Drawings of a cheese cut: side views of the cut plane (x-y) coloured by damage, with the wire, and the
force-depth curve (matplotlib, imported lazily)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.results import Rendering, Trajectory, frame_selection
from invphys_cheese_cut.scene import GAP

ANIMATIONS = ("gif", "mp4", "none")


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _frame(traj: Trajectory, k: int, path: Path, limits: tuple[np.ndarray, np.ndarray]) -> Path:
    plt = _pyplot()
    assert traj.positions is not None and traj.damage is not None and traj.frame_indices is not None
    x, d = traj.positions[k], traj.damage[k]
    t = float(traj.frame_indices[k]) / float(traj.fps or 1.0)
    depth = float(traj.series["wire_depth"].at(t)) if "wire_depth" in traj.series else 0.0
    fig, ax = plt.subplots(figsize=(5.0, 3.6), dpi=100)
    order = np.argsort(x[:, 2])  # draw the front (large z) last
    sc = ax.scatter(x[order, 0] * 1e3, x[order, 1] * 1e3, c=d[order], cmap="YlOrRd", vmin=0.0, vmax=1.0, s=6,
                    edgecolors="none")
    cx, y0, r = (float(traj.extra.get(k_, 0.0)) for k_ in ("centre_x", "wire_start_y", "wire_radius"))
    ax.add_patch(plt.Circle((cx * 1e3, (y0 - depth - GAP) * 1e3), r * 1e3, color="0.3"))
    lo, hi = limits
    ax.set_xlim(lo[0] * 1e3, hi[0] * 1e3)
    ax.set_ylim(lo[1] * 1e3, hi[1] * 1e3)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"t = {t:.3f} s")
    fig.colorbar(sc, ax=ax, label="damage")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _force_curve(traj: Trajectory, path: Path) -> Path | None:
    if "wire_force" not in traj.series or "wire_depth" not in traj.series:
        return None
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 3.4), dpi=100)
    ax.plot(traj.series["wire_depth"].values * 1e3, traj.series["wire_force"].values, marker=".")
    ax.set_xlabel("wire depth below the top surface (mm)")
    ax.set_ylabel("force on the wire (N)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def render_cut(traj: Trajectory, out: str | Path, *, max_frames: int = 60, animation: str = "gif",
               **options: Any) -> Rendering:
    """Write ``frame_XXXX.png`` side views (at most ``max_frames``, ending on the last), an animation, and
    ``force_depth.png`` under ``out``; takes no ``options``."""
    if options:
        raise InvphysError(f"the cheese-cut renderer takes no options (got {', '.join(sorted(options))})")
    if animation not in ANIMATIONS:
        raise InvphysError(f"animation must be one of {', '.join(ANIMATIONS)}, not {animation!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result = Rendering()
    if traj.positions is not None and traj.damage is not None:
        pts = traj.positions.reshape(-1, 3)
        pad = 0.01
        limits = (pts.min(axis=0) - pad, np.maximum(pts.max(axis=0), float(traj.extra.get("wire_start_y", 0))) + pad)
        for k in frame_selection(traj.n_frames, max_frames):
            result.images.append(_frame(traj, int(k), out / f"frame_{int(k):04d}.png", limits))
        if animation != "none" and len(result.images) > 1:
            from invphys.core.trajectory_plot import write_animation

            result.animation = write_animation(result.images, out / f"animation.{animation}")
    curve = _force_curve(traj, out / "force_depth.png")
    if curve is not None:
        result.images.append(curve)
    return result
