"""Drawings of toy-spring runs: the mass on its spring, frame by frame, and the series plotted."""

from pathlib import Path

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.results import Rendering, frame_selection
from invphys.core.trajectory_plot import plot_series, write_animation


def render_spring(traj, out, *, max_frames, animation):
    """Write ``frame_XXXX.png`` (at most ``max_frames``), an animation and ``series.png`` under ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if animation not in ("gif", "mp4", "none"):
        raise InvphysError(f"animation must be gif, mp4 or none, not {animation!r}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    x = traj.series["displacement"]
    done = Rendering()
    for i in frame_selection(len(x), max_frames):
        end = 0.2 + float(x.values[i])  # the mass rests 0.2 m from the wall
        zigzag = np.linspace(0.0, end, 22)
        fig, ax = plt.subplots(figsize=(4.0, 1.6))
        ax.plot(zigzag, 0.02 * (-1.0) ** np.arange(22) * (np.arange(22) % 21 > 0), color="0.3")
        ax.add_patch(plt.Rectangle((end, -0.04), 0.05, 0.08, color="tab:blue"))
        ax.axvline(0.0, color="k", lw=3)
        ax.set_xlim(-0.02, 0.32)
        ax.set_ylim(-0.08, 0.08)
        ax.set_axis_off()
        ax.set_title(f"t = {x.times[i]:.2f} s", fontsize=9)
        done.images.append(out / f"frame_{i:04d}.png")
        fig.savefig(done.images[-1], dpi=80)
        plt.close(fig)
    if animation != "none" and len(done.images) > 1:
        done.animation = write_animation(done.images, out / f"animation.{animation}")
    series = plot_series({"run": traj}, out / "series.png")
    if series is not None:
        done.images.append(series)
    return done
