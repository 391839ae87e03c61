"""Generic drawings of any :class:`~invphys.core.results.Trajectory` (matplotlib, imported lazily).

:func:`render_trajectory` is what :meth:`Simulator.render <invphys.core.interfaces.Simulator.render>`
does for a simulator that has no renderer of its own: particle frames as x-y scatters coloured by
damage (or region label), and every time series in one plot. :func:`plot_series` overlays the series
of several trajectories (the report's target vs recovered plots).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.results import Rendering, Trajectory, frame_selection

ANIMATIONS = ("gif", "mp4", "none")
#: at most this many series are drawn in one plot (the first ones, in the trajectory's order)
MAX_SERIES_PLOTS = 12


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_series(trajectories: Mapping[str, Trajectory], path: str | Path, names: list[str] | None = None,
                title: str = "") -> Path | None:
    """One panel per series name, each trajectory (keyed by its legend label) drawn in it.

    ``names`` defaults to the series the trajectories share (in the first one's order), capped at
    :data:`MAX_SERIES_PLOTS`. Returns the PNG's path, or None when there is nothing to draw.
    """
    trajs = list(trajectories.values())
    if not trajs:
        return None
    if names is None:
        names = [n for n in trajs[0].series if all(n in t.series for t in trajs)]
    names = names[:MAX_SERIES_PLOTS]
    if not names:
        return None
    plt = _pyplot()
    cols = min(3, len(names))
    rows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
    for ax, name in zip(axes.ravel(), names, strict=False):
        unit = ""
        for label, traj in trajectories.items():
            s = traj.series.get(name)
            if s is None:
                continue
            unit = s.unit or unit
            values = s.values.astype(np.float64)
            if values.ndim == 1:
                ax.plot(s.times, values, label=label)
            else:
                for k in range(values.shape[1]):
                    ax.plot(s.times, values[:, k], label=f"{label} [{k}]")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("time (s)")
        ax.set_ylabel(unit)
        if len(trajectories) > 1 or any(t.series[name].values.ndim > 1 for t in trajs if name in t.series):
            ax.legend(fontsize=7)
    for ax in axes.ravel()[len(names):]:
        ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _particle_frames(traj: Trajectory, out: Path, index: np.ndarray) -> list[Path]:
    plt = _pyplot()
    assert traj.positions is not None and traj.frame_indices is not None and traj.fps
    pos = traj.positions[index].astype(np.float64)
    finite = pos[np.isfinite(pos).all(axis=2)]
    lo, hi = (finite.min(axis=0), finite.max(axis=0)) if len(finite) else (np.zeros(3), np.ones(3))
    pad = 0.05 * max(float(np.max(hi - lo)), 1e-9)
    paths = []
    for j, i in enumerate(index):
        fig, ax = plt.subplots(figsize=(4.8, 4.0))
        if traj.damage is not None:
            colour, cmap, vmax = traj.damage[i], "plasma", 1.0
        elif traj.labels is not None:
            colour, cmap, vmax = traj.labels, "tab10", 9.0
        else:
            colour, cmap, vmax = np.zeros(traj.n_particles), "viridis", 1.0
        ax.scatter(pos[j, :, 0], pos[j, :, 1], c=colour, cmap=cmap, vmin=0.0, vmax=vmax, s=4)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal", adjustable="datalim")
        frame = int(traj.frame_indices[i])
        ax.set_title(f"frame {frame}  t = {frame / traj.fps:.3g} s", fontsize=10)
        p = out / f"frame_{frame:04d}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
    return paths


def write_animation(images: list[Path], path: Path, fps: float = 6.0) -> Path:
    """A GIF (``.gif``) or MP4 (``.mp4``, needs imageio-ffmpeg) of PNG ``images``."""
    import imageio.v2 as imageio

    frames: list[Any] = [imageio.imread(p) for p in images]
    if path.suffix == ".mp4":
        imageio.mimsave(path, frames, fps=fps)
    else:
        imageio.mimsave(path, frames, duration=1.0 / fps, loop=0)
    return path


def render_trajectory(traj: Trajectory, out: str | Path, *, max_frames: int = 60,
                      animation: str = "gif", title: str = "") -> Rendering:
    """Draw ``traj`` under the directory ``out``: at most ``max_frames`` particle frames
    (``frame_XXXX.png``, evenly spread, ending on the last), an animation of them, and ``series.png``
    with every time series."""
    if animation not in ANIMATIONS:
        from invphys.core.errors import InvphysError

        raise InvphysError(f"animation must be one of {', '.join(ANIMATIONS)}, not {animation!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result = Rendering()
    if traj.has_particles:
        result.images += _particle_frames(traj, out, frame_selection(traj.n_frames, max_frames))
        if animation != "none" and len(result.images) > 1:
            result.animation = write_animation(result.images, out / f"animation.{animation}")
    series = plot_series({"run": traj}, out / "series.png", title=title)
    if series is not None:
        result.images.append(series)
    return result
