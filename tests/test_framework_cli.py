"""``invphys simulate`` / ``invphys render`` for any simulator: no example assumed, the render hook, frame caps."""

from __future__ import annotations

import json

import numpy as np
import pytest
from core_plugins import LineSimulator
from pydantic import Field
from typer.testing import CliRunner

from invphys import registry
from invphys.cli import app
from invphys.core.interfaces import PluginConfig, Simulator
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.results import RunStats, SimulationResult, Trajectory
from invphys.core.trajectory_io import load_trajectory, read_header

runner = CliRunner()


class RampSimulator(Simulator):
    """A lumped model: a force ramping up at a parameter-dependent rate (time series only, no particles)."""

    name = "test_ramp"
    version = "3"

    class Config(PluginConfig):
        samples: int = Field(50, ge=2)

    def parameter_space(self) -> ParameterSpace:
        return ParameterSpace((Parameter("rate", 0.5, 5.0, unit="N/s"),))

    def simulate(self, params, on_result=None):
        p = np.atleast_2d(self.parameter_space().check(params))
        out = []
        for i, (rate,) in enumerate(p):
            traj = Trajectory()
            t = np.linspace(0.0, 2.0, self.config.samples)
            traj.add_series("force", t, rate * t, unit="N")
            res = SimulationResult(params=p[i], ok=True, trajectory=traj,
                                   stats=RunStats(backend="numpy", simulator=self.name, simulator_version="3"))
            if on_result:
                on_result(i, res)
            out.append(res)
        return out


class ManyFramesLine(LineSimulator):
    """The line simulator with a thousand frames (a render must not draw them all)."""

    name = "test_many_frames"

    class Config(PluginConfig):
        frames: int = Field(1000, gt=1)


@pytest.fixture
def only(monkeypatch):
    """Make the default registry hold exactly the given simulators (no entry points)."""

    def install(*classes):
        monkeypatch.setattr(registry, "_default", registry.Registry(autoload=False))
        return registry.registered(*classes)

    return install


def test_simulate_uses_the_only_installed_simulator_and_records_it(tmp_path, only) -> None:
    with only(RampSimulator):
        res = runner.invoke(app, ["simulate", "--params", '{"rate": 2}', "--out", str(tmp_path / "s"), "--render",
                                  "--json"])
        assert res.exit_code == 0, res.output
        summary = json.loads(res.stdout)
        assert summary["simulator"]["simulator"] == "test_ramp"
        run = tmp_path / "s" / "run_000"
        traj = load_trajectory(run)
        assert not traj.has_particles
        np.testing.assert_allclose(traj.series["force"].values[-1], 4.0)
        assert read_header(run / "trajectory.npz")["simulator"]["config"] == {"samples": 50}
        # the generic renderer: no particle frames, one plot of the series
        assert sorted(p.name for p in (run / "render").iterdir()) == ["series.png"]
        # render finds the simulator in the file; unknown options of the generic renderer are one line
        res = runner.invoke(app, ["render", str(run), "--out", str(tmp_path / "r"), "--json"])
        assert res.exit_code == 0, res.output
        assert json.loads(res.stdout)["simulator"] == "test_ramp"
        res = runner.invoke(app, ["render", str(run), "--out", str(tmp_path / "r2"), "--option", "azim=30"])
        assert res.exit_code == 2 and "takes no options (got azim)" in res.output
    # a file from a simulator that is not installed here still draws, generically
    with only(LineSimulator):
        res = runner.invoke(app, ["render", str(run), "--out", str(tmp_path / "r3"), "--json"])
        assert res.exit_code == 0, res.output
        assert json.loads(res.stdout)["simulator"] == "generic renderer (test_ramp is not installed)"
        assert (tmp_path / "r3" / "series.png").is_file()


def test_simulate_without_a_simulator_name_is_clear_when_ambiguous_or_empty(tmp_path, only) -> None:
    with only(RampSimulator, LineSimulator):
        res = runner.invoke(app, ["simulate", "--out", str(tmp_path)])
        assert res.exit_code == 2
        assert "several simulators are installed (test_line, test_ramp): name one with --simulator" in res.output
    with only():
        res = runner.invoke(app, ["simulate", "--out", str(tmp_path)])
        assert res.exit_code == 2 and "no simulator plugin is installed" in res.output


def test_render_caps_frames(tmp_path, only) -> None:
    with only(ManyFramesLine):
        res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "s"), "--render", "--max-frames", "4",
                                  "--json"])
        assert res.exit_code == 0, res.output
        render = tmp_path / "s" / "run_000" / "render"
        frames = sorted(p.name for p in render.glob("frame_*.png"))
        assert frames == ["frame_0000.png", "frame_0333.png", "frame_0666.png", "frame_0999.png"]
        assert (render / "animation.gif").is_file() and len(list(render.iterdir())) == 5
        res = runner.invoke(app, ["render", str(tmp_path / "s" / "run_000"), "--out", str(tmp_path / "one"),
                                  "--max-frames", "1", "--animation", "none", "--json"])
        assert res.exit_code == 0, res.output
        assert [p.name for p in (tmp_path / "one").iterdir()] == ["frame_0999.png"]  # the final state
        res = runner.invoke(app, ["render", str(tmp_path / "s" / "run_000"), "--out", str(tmp_path / "x"),
                                  "--max-frames", "0"])
        assert res.exit_code == 2 and "--max-frames must be at least 1" in res.output


def test_render_option_values_parse_as_json() -> None:
    from invphys.cli.render import parse_options
    from invphys.core.errors import InvphysError

    assert parse_options(["azim=30", "ply=false", "size=[160, 120]", "name=x"]) == {
        "azim": 30, "ply": False, "size": [160, 120], "name": "x"}
    with pytest.raises(InvphysError, match="is not KEY=VALUE"):
        parse_options(["azim"])
