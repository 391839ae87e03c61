"""The report draws any simulator's runs: final states through Simulator.render, time series overlaid; a
drawing or figure that fails is a warning in a finished run's report; the report's counts, drawings,
parameter order and figure labels tell the truth (a real pipeline over four targets)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from core_plugins import LineSimulator
from test_dataset_toy import ToyOscillator
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


# -- a finished run's report tells the truth and survives its plugins' drawings --------------------------

class HalfDrawnOscillator(ToyOscillator):
    """The toy oscillator whose own renderer raises on its 3rd call (target 1's first final state)."""

    name = "test_half_drawn_oscillator"
    calls = 0

    def render(self, trajectory, path, *, max_frames=60, animation="gif", **options):
        type(self).calls += 1
        if type(self).calls == 3:
            raise RuntimeError("the renderer's own bug")
        from invphys.core.trajectory_plot import render_trajectory

        return render_trajectory(trajectory, path, max_frames=max_frames, animation=animation)


SPEC = """
name: report-truth
seed: 3
simulator: {type: "test_framework_report:HalfDrawnOscillator"}
dataset: {n: 120, batch_size: 60}
surrogate: {type: ensemble, members: 2, hidden: [16, 16, 8], max_epochs: 20, patience: 5, dropout: 0.0}
optimizers:
  cma: {type: cma_es, budget: 40}
targets: {n: 4, validate: 4}
evaluation:
  baselines:
    nearest_neighbour: {type: nearest_neighbour}
  bootstrap: 100
validator: {type: simulator, batch_size: 16}
report: {render: true}
"""


def _run(out, **kwargs):
    import io

    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    return run_spec(parse_spec(SPEC), out, progress=False, console=Console(file=io.StringIO()), **kwargs)


@pytest.fixture(scope="module")
def report_run(tmp_path_factory):
    """A real pipeline over 4 targets whose simulator's render raises for target 1 (before: an internal
    error of the report stage after every simulation was done)."""
    out = tmp_path_factory.mktemp("report") / "run"
    HalfDrawnOscillator.calls = 0
    _run(out)
    return out / "report"


def test_a_render_that_raises_is_a_warning_in_the_report_not_a_failure(report_run) -> None:
    md = (report_run / "report.md").read_text()
    rep = json.loads((report_run / "report.json").read_text())
    assert (report_run.parent / "report" / "DONE.json").is_file()
    (warning,) = rep["warnings"]
    assert warning.startswith("target 1: final states not drawn") and "the renderer's own bug" in warning
    assert "## Warnings" in md and "the renderer's own bug" in md
    assert (report_run / "renders" / "t00.png").is_file() and (report_run / "renders" / "t02.png").is_file()
    assert not (report_run / "renders" / "t01.png").exists()
    assert "## Summary (targets)" in md and "## Recovered parameters" in md


def test_a_report_figure_that_fails_is_a_warning(report_run, monkeypatch, tmp_path) -> None:
    import shutil

    import invphys.evaluation.plots as plots

    def broken(*args, **kwargs):
        raise ValueError("cannot draw this")

    monkeypatch.setattr(plots, "plot_protocol", broken)
    HalfDrawnOscillator.calls = 10   # its render works from now on
    shutil.copytree(report_run.parent, tmp_path / "run")
    _run(tmp_path / "run", stages=["report"], force=["report"])
    rep = json.loads((tmp_path / "run" / "report" / "report.json").read_text())
    assert rep["warnings"] == ["protocol.png not drawn (ValueError: cannot draw this)"]
    md = (tmp_path / "run" / "report" / "report.md").read_text()
    assert "protocol.png not drawn" in md and "![protocol]" not in md and "![recovery](recovery.png)" in md


def test_the_report_says_which_targets_it_draws(report_run) -> None:
    md = (report_run / "report.md").read_text()
    assert "4 held-out targets" in md
    # target 3: the validate stage kept no runs of it; target 1: its simulator's render failed (a warning)
    assert "Drawings (target vs recovered): 2 of 4 targets (0, 2)" in md and "first 3 targets" in md
    assert "| nearest_neighbour | nearest_neighbour | raw | dataset | 0 |" in md   # a count, not "0.000"


def test_parameters_are_listed_in_the_parameter_spaces_order(report_run) -> None:
    order = ["k", "c", "m"]   # the toy's space; alphabetical would be c, k, m
    assert list(ToyOscillator().parameter_space().names) == order
    header = (report_run / "report.csv").read_text().splitlines()[0].split(",")
    assert [h for h in header if h.startswith("param_")] == [f"param_{n}" for n in order]
    rep = json.loads((report_run / "report.json").read_text())
    assert [k for k in rep["rows"][0] if k.startswith("param_")] == [f"param_{n}" for n in order]
    assert rep["parameters"]["names"] == order


def _text_overlaps(fig) -> list[tuple[str, str]]:
    """Pairs of drawn texts (tick labels in view, axis labels, legends) whose boxes overlap."""
    import matplotlib.text
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)   # a closed figure keeps no canvas of its own
    canvas.draw()
    renderer = canvas.get_renderer()
    texts = []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                if lo - 1e-9 <= tick.get_loc() <= hi + 1e-9 and tick.label1.get_visible():
                    texts.append(tick.label1)
            texts.append(axis.label)
        texts += [t for t in ax.findobj(matplotlib.text.Text) if t.axes is ax and t in ax.texts]
        if ax.get_legend() is not None:
            texts += ax.get_legend().get_texts()
    boxes = [(t.get_text(), t.get_window_extent(renderer).shrunk(0.98, 0.9)) for t in texts
             if t.get_visible() and t.get_text().strip()]
    return [(a, b) for i, (a, ba) in enumerate(boxes) for b, bb in boxes[i + 1:] if ba.overlaps(bb)]


def test_recovery_png_has_no_overlapping_labels(tmp_path, monkeypatch) -> None:
    """Eight methods with long names and histories over five decades (a quick start's report): the bars'
    rotated names used to overlap each other."""
    from matplotlib.figure import Figure

    from invphys.pipeline.stages.report import plot_recovery

    saved = []
    original = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: (saved.append(self), original(self, *a, **k))[1])
    rows = []
    for label, budget in [("cma_es_raw", 2000), ("cma_es_latent", 2000), ("nevergrad_ngopt", 1500),
                          ("ppo_goal_conditioned", 100000), ("nearest_neighbour", 0), ("npe_best64", 0),
                          ("nearest_neighbour_k5", 0), ("cma_from_nn_simulator", 60)]:
        for k in range(4):
            evals = np.unique(np.geomspace(8, max(budget, 8), 12).astype(int)) if budget else []
            rows.append({"optimizer": label, "type": "x", "space": "raw", "evaluator": "shared",
                         "problem": "target", "target_index": k, "evaluations": budget, "wall_time_s": 1.0,
                         "r_surrogate": 0.6, "r_actual": 0.5, "gap": 0.1, "failure": None, "validated": True,
                         "history": [[int(e), 0.3 + 0.01 * i] for i, e in enumerate(evals)]})
    assert plot_recovery(rows, tmp_path / "recovery.png") == tmp_path / "recovery.png"
    (fig,) = saved
    assert _text_overlaps(fig) == []
