"""The report draws any simulator's runs: final states through Simulator.render, time series overlaid."""

from __future__ import annotations

import numpy as np
from core_plugins import LineSimulator
from test_framework_cli import RampSimulator

from invphys.core.results import Rendering, Trajectory
from invphys.core.trajectory_plot import plot_series
from invphys.pipeline.stages.report import render_final_state


class DrawnRamp(RampSimulator):
    """The ramp with its own renderer, which records how it was called."""

    name = "test_drawn_ramp"
    calls: list[dict] = []

    def render(self, trajectory, path, *, max_frames=60, animation="gif", **options):
        type(self).calls.append({"max_frames": max_frames, "animation": animation})
        path.mkdir(parents=True, exist_ok=True)
        image = plot_series({"run": trajectory}, path / "mine.png")
        return Rendering(images=[image])


def test_final_states_use_the_simulators_renderer_with_one_frame(tmp_path) -> None:
    traj = RampSimulator().simulate([[2.0]])[0].trajectory
    out = render_final_state(DrawnRamp(), traj, tmp_path / "a.png", "target 0")
    assert out == tmp_path / "a.png" and out.stat().st_size > 1000
    assert DrawnRamp.calls[-1] == {"max_frames": 1, "animation": "none"}
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # the renderer's folder is cleaned up


def test_series_only_runs_without_a_renderer_are_plotted_not_drawn(tmp_path) -> None:
    traj = RampSimulator().simulate([[2.0]])[0].trajectory
    assert render_final_state(RampSimulator(), traj, tmp_path / "a.png", "t") is None
    particles = LineSimulator(frames=30).simulate([[1.0, 0.0]])[0].trajectory
    assert render_final_state(LineSimulator(), particles, tmp_path / "b.png", "t") == tmp_path / "b.png"
    assert render_final_state(None, particles, tmp_path / "c.png", "t") == tmp_path / "c.png"


def test_series_plots_overlay_shared_series_only(tmp_path) -> None:
    t = np.linspace(0, 1, 5)
    a, b = Trajectory(), Trajectory()
    a.add_series("force", t, t, unit="N")
    a.add_series("only_in_a", t, t)
    b.add_series("force", t, 2 * t, unit="N")
    assert plot_series({"target": a, "recovered": b}, tmp_path / "s.png") == tmp_path / "s.png"
    assert plot_series({"target": a, "recovered": Trajectory()}, tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()
