"""Adaptive design (``dataset.adaptive``): rounds of runs where a surrogate ensemble is least sure.

``FrontSim`` is a two-parameter model whose response is flat for most of the square and grows steeply
and wavily as ``a`` nears 1 (like features whose heavy tails sit at extreme parameters), so a surrogate
learnt from uniform points is unsure there. The adaptive rounds must put their runs there, give a better
surrogate than as many uniform runs, resume the same points after a kill, and refuse other settings.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from invphys.core.adaptive_plan import PLAN_FILE, pick_spread
from invphys.core.dataset import DatasetStore
from invphys.core.errors import InvphysError
from invphys.core.interfaces import FeatureExtractor, PluginConfig, Simulator
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.results import RunStats, SimulationResult, TimeSeries, Trajectory
from invphys.core.sampling import sample_unit
from invphys.core.spec import validate_spec
from invphys.data.generate import generate_dataset

TESTS = str(Path(__file__).resolve().parent)
SIM = "test_dataset_adaptive:FrontSim"
FEATURES = "test_dataset_adaptive:FrontFeatures"
SURROGATE = {"type": "ensemble", "members": 3, "hidden": [32, 32, 32], "max_epochs": 300, "patience": 300}
ADAPTIVE = {"initial": 40, "rounds": 2, "surrogate": SURROGATE, "candidates": 30, "min_gap": 0.02}


class FrontSim(Simulator):
    """``y(t) = t exp(10 (a - 1)) cos(6 b) + 0.1 b`` over a few frames (a, b in [0, 1])."""

    name = "front_sim"
    version = "1"

    class Config(PluginConfig):
        sleep_s: float = 0.0

    def parameter_space(self) -> ParameterSpace:
        return ParameterSpace((Parameter("a", 0.0, 1.0), Parameter("b", 0.0, 1.0)))

    def default_feature_extractor(self) -> str | None:
        return FEATURES

    def simulate(self, params, on_result=None):
        p = np.atleast_2d(self.parameter_space().check(params))
        out = []
        for i, (a, b) in enumerate(p):
            time.sleep(self.config.sleep_s)
            t = np.linspace(0.0, 1.0, 5)
            v = t * np.exp(10.0 * (a - 1.0)) * np.cos(6.0 * b) + 0.1 * b
            res = SimulationResult(params=p[i], ok=True, stats=RunStats(backend="numpy", device="cpu"),
                                   trajectory=Trajectory(series={"y": TimeSeries(t, v)}))
            if on_result is not None:
                on_result(i, res)
            out.append(res)
        return out


class FrontFeatures(FeatureExtractor):
    name = "front_features"

    class Config(PluginConfig):
        pass

    @property
    def feature_names(self) -> tuple[str, ...]:
        return ("y_end", "y_mean")

    def extract(self, trajectory: Trajectory) -> np.ndarray:
        v = trajectory.series["y"].values
        return np.array([v[-1], v.mean()])


def _generate(path: Path, n: int = 80, **kw):
    return generate_dataset(path, simulator={"type": SIM}, n=n, batch_size=10, seed=1, progress=False,
                            adaptive=ADAPTIVE, **kw)


def _response(theta: np.ndarray) -> np.ndarray:
    t = np.linspace(0.0, 1.0, 5)
    v = t * (np.exp(10.0 * (theta[:, :1] - 1.0)) * np.cos(6.0 * theta[:, 1:])) + 0.1 * theta[:, 1:]
    return np.stack([v[:, -1], v.mean(axis=1)], axis=1)


def test_adaptive_rounds_put_their_runs_where_the_response_is_steep(tmp_path) -> None:
    summary = _generate(tmp_path / "ds")
    assert summary.complete and summary.stop_reason == "complete"
    assert (summary.ran, summary.ok, summary.total_rows) == (80, 80, 80)
    store = DatasetStore(tmp_path / "ds")
    index = store.frame()["sample_index"].to_numpy()  # both sorted by key
    assert sorted(index) == list(range(80))
    theta = store.arrays().theta[np.argsort(index)]
    # the first 40 are the sampler's uniform design, unchanged
    np.testing.assert_allclose(theta[:40], sample_unit(40, 2, "uniform", 1), atol=1e-6)
    steep = lambda x: (x[:, 0] > 0.8).mean()  # noqa: E731 - 20 % of the square
    assert steep(theta[:40]) < 0.4
    assert steep(theta[40:]) > 0.6, steep(theta[40:])
    np.testing.assert_allclose(store.arrays().y[np.argsort(index)], _response(theta), atol=1e-5)

    # a better surrogate than 80 uniform runs (same plugin, same settings), on 2,000 fresh points
    from invphys.models.data import r2_scores
    from invphys.registry import create

    test = np.random.default_rng(5).random((2000, 2))
    scores = []
    for rows in (theta, sample_unit(80, 2, "uniform", 1)):
        model = create("surrogate", SURROGATE)
        model.fit(rows, _response(rows))
        scores.append(r2_scores(_response(test), model.predict(test))[0])
    assert scores[0] > scores[1] + 0.05, scores
    plan = json.loads((tmp_path / "ds" / PLAN_FILE).read_text())
    assert [len(r["points"]) for r in plan["rounds"]] == [20, 20]
    assert [r["record"]["training_rows"] for r in plan["rounds"]] == [40, 60]
    rounds = [s.get("design") for s in DatasetStore(tmp_path / "ds").metadata["sessions"]]
    assert rounds == [{"adaptive": "initial"}, {"adaptive": "round", "round": 0}, {"adaptive": "round", "round": 1}]
    assert [r["round"] for r in summary.design["rounds"]] == [0, 1]
    info = store.info()["design"]  # what `invphys dataset info` shows
    assert info["adaptive"]["initial"] == 40 and [r["training_rows"] for r in info["rounds"]] == [40, 60]

    again = _generate(tmp_path / "ds")  # a re-run finds everything stored and trains nothing
    assert (again.ran, again.already_present, again.other_rows, again.complete) == (0, 80, 0, True)


def test_other_adaptive_settings_are_refused_and_rows_kept(tmp_path) -> None:
    _generate(tmp_path / "ds")
    before = DatasetStore(tmp_path / "ds").content_fingerprint()
    with pytest.raises(InvphysError, match="other adaptive settings"):
        generate_dataset(tmp_path / "ds", simulator={"type": SIM}, n=80, batch_size=10, seed=1, progress=False,
                         adaptive={**ADAPTIVE, "min_gap": 0.1})
    assert DatasetStore(tmp_path / "ds").content_fingerprint() == before


def test_pick_spread_keeps_the_gap_then_fills_with_the_best() -> None:
    pts = np.array([[0.0, 0.0], [0.01, 0.0], [0.5, 0.5], [0.02, 0.0]])
    score = np.array([4.0, 3.0, 1.0, 2.0])
    assert pick_spread(pts, score, 2, 0.1).tolist() == [0, 2]
    assert pick_spread(pts, score, 3, 0.1).tolist() == [0, 2, 1]  # too few far apart: the best of the rest


def test_spec_checks_the_adaptive_block() -> None:
    base = {"name": "a", "simulator": {"type": SIM}, "dataset": {"n": 10}}
    ok = validate_spec({**base, "dataset": {"n": 10, "adaptive": {"rounds": 2}}}, references=False)
    assert ok.dataset.adaptive.surrogate == {"type": "ensemble"}
    for bad, match in [({"initial": 10}, "initial"), ({"rounds": 9}, "rounds"), ({"surrogate": {}}, "type"),
                       ({"roundz": 2}, "roundz")]:
        with pytest.raises(InvphysError, match=match):
            validate_spec({**base, "dataset": {"n": 10, "adaptive": bad}}, references=False)


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")]),
            "INVPHYS_DISABLE_PLUGIN_AUTOLOAD": "1"}


def _slow_generation(tmp_path: Path, name: str) -> tuple[Path, list[str]]:
    """(store, CLI command) of an 80-run adaptive design with a slow simulator (0.05 s per run)."""
    spec, out = tmp_path / "spec.yaml", tmp_path / "ds"
    spec.write_text(yaml.safe_dump({
        "name": name, "seed": 1, "stages": ["dataset"],
        "simulator": {"type": SIM, "sleep_s": 0.05}, "executor": {"type": "local"},
        "dataset": {"n": 80, "batch_size": 5, "adaptive": ADAPTIVE}}))
    return out, [sys.executable, "-m", "invphys.cli", "dataset", "generate", str(spec), "--out", str(out),
                 "--no-progress", "--json"]


def test_killed_in_a_round_resumes_the_same_points(tmp_path) -> None:
    out, cmd = _slow_generation(tmp_path, "adaptive-kill")
    proc = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out / PLAN_FILE).exists() or DatasetStore(out).info()["rows"] < 45:
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "the first round never started"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    planned = json.loads((out / PLAN_FILE).read_text())["rounds"][0]["points"]
    stored = DatasetStore(out).info()["rows"]
    assert 45 <= stored < 80

    done = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["complete"] and summary["total_rows"] == 80 and summary["already_present"] >= stored
    plan = json.loads((out / PLAN_FILE).read_text())
    assert plan["rounds"][0]["points"] == planned  # the killed round's points, not a refit's
    data = DatasetStore(out).arrays()
    keys = {tuple(np.round(t, 6)) for t in data.theta}
    assert all(tuple(np.round(p, 6)) in keys for r in plan["rounds"] for p in r["points"])


def test_the_dataset_stage_generates_an_adaptive_design_and_keys_it(tmp_path) -> None:
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    base = {"name": "adaptive-stage", "seed": 1, "stages": ["dataset"], "simulator": {"type": SIM}}
    spec = parse_spec(yaml.safe_dump({**base, "dataset": {"n": 60, "batch_size": 10,
                                                          "adaptive": {**ADAPTIVE, "initial": 30}}}))
    first = run_spec(spec, tmp_path / "run", progress=False)
    assert first["dataset"]["total_rows"] == 60 and len(first["dataset"]["design"]["rounds"]) == 2
    assert (tmp_path / "run" / "dataset" / "store" / PLAN_FILE).exists()
    # the adaptive block is part of the stage's key; a spec without it keeps the keys it always had
    assert "adaptive" in spec.section_dump(["dataset"])["dataset"]
    plain = parse_spec(yaml.safe_dump({**base, "dataset": {"n": 60, "batch_size": 10}}))
    assert plain.dataset.adaptive is None and "adaptive" not in plain.section_dump(["dataset"])["dataset"]


def test_bad_adaptive_input_fails_before_simulating_and_keeps_rows(tmp_path) -> None:
    with pytest.raises(InvphysError, match="member uncertainty"):
        generate_dataset(tmp_path / "a", simulator={"type": SIM}, n=20, seed=1, progress=False,
                         adaptive={**ADAPTIVE, "initial": 10, "surrogate": {"type": "mlp"}})
    assert not (tmp_path / "a").exists() or not list((tmp_path / "a").glob("part-*"))
    with pytest.raises(InvphysError, match="surrogate"):
        generate_dataset(tmp_path / "b", simulator={"type": SIM}, n=20, seed=1, progress=False,
                         adaptive={**ADAPTIVE, "initial": 10, "surrogate": {"type": "no_such_model"}})
    with pytest.raises(InvphysError, match="roundz"):  # from Python too, checked like a spec's block
        generate_dataset(tmp_path / "c", simulator={"type": SIM}, n=20, seed=1, progress=False,
                         adaptive={"roundz": 2})
    assert not (tmp_path / "c").exists()
    _generate(tmp_path / "ds")
    before = DatasetStore(tmp_path / "ds").content_fingerprint()
    (tmp_path / "ds" / PLAN_FILE).write_text("{not json")
    with pytest.raises(InvphysError, match="unreadable"):
        _generate(tmp_path / "ds")
    assert DatasetStore(tmp_path / "ds").content_fingerprint() == before


def test_a_time_limit_stops_the_design_and_a_rerun_finishes_it(tmp_path) -> None:
    path = tmp_path / "ds"
    kw = {"simulator": {"type": SIM, "sleep_s": 0.02}, "n": 80, "batch_size": 10, "seed": 1, "progress": False,
          "adaptive": ADAPTIVE}
    first = generate_dataset(path, limit_minutes=0.01, **kw)
    assert first.stop_reason == "time_limit" and not first.complete and 0 < first.total_rows < 80
    done = generate_dataset(path, **kw)
    assert done.complete and done.total_rows == 80 and done.already_present == first.total_rows


def test_raising_n_and_rounds_adds_rounds_and_keeps_the_planned_points(tmp_path) -> None:
    _generate(tmp_path / "ds")
    planned = json.loads((tmp_path / "ds" / PLAN_FILE).read_text())["rounds"]
    before = DatasetStore(tmp_path / "ds").content_fingerprint()
    with pytest.raises(InvphysError, match="raise `rounds`"):  # more runs, no more rounds
        _generate(tmp_path / "ds", n=100)
    assert DatasetStore(tmp_path / "ds").content_fingerprint() == before
    grown = generate_dataset(tmp_path / "ds", simulator={"type": SIM}, n=100, batch_size=10, seed=1, progress=False,
                             adaptive={**ADAPTIVE, "rounds": 3})
    assert grown.complete and (grown.ran, grown.already_present, grown.total_rows) == (20, 80, 100)
    plan = json.loads((tmp_path / "ds" / PLAN_FILE).read_text())
    assert plan["rounds"][:2] == planned and len(plan["rounds"][2]["points"]) == 20
    assert (plan["key"]["n"], plan["key"]["rounds"]) == (100, 3)
    assert plan["rounds"][2]["record"]["training_rows"] == 80


def test_a_design_with_the_default_initial_grows_without_restating_it(tmp_path) -> None:
    """``initial`` left out is n // 2 for a new design but the stored plan's when a design grows (n // 2 of the
    larger n would be other settings); stated differently, it is still refused."""
    block = {k: v for k, v in ADAPTIVE.items() if k != "initial"}
    first = generate_dataset(tmp_path / "ds", simulator={"type": SIM}, n=80, batch_size=10, seed=1, progress=False,
                             adaptive=block)
    assert first.complete and json.loads((tmp_path / "ds" / PLAN_FILE).read_text())["key"]["initial"] == 40
    with pytest.raises(InvphysError, match="other adaptive settings"):
        generate_dataset(tmp_path / "ds", simulator={"type": SIM}, n=100, batch_size=10, seed=1, progress=False,
                         adaptive={**block, "rounds": 3, "initial": 50})
    grown = generate_dataset(tmp_path / "ds", simulator={"type": SIM}, n=100, batch_size=10, seed=1, progress=False,
                             adaptive={**block, "rounds": 3})
    assert grown.complete and (grown.ran, grown.total_rows) == (20, 100)
    assert json.loads((tmp_path / "ds" / PLAN_FILE).read_text())["key"]["initial"] == 40


def test_a_second_process_growing_the_same_design_is_refused_until_the_first_dies(tmp_path) -> None:
    """The store's write lock is released while a round's surrogate trains; the design lock is not, so a second
    generation fails with one line (exit 2) instead of planning the same round again, and a SIGKILLed holder
    leaves no stale lock behind."""
    out, cmd = _slow_generation(tmp_path, "adaptive-twice")
    first = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out / "_metadata.json").exists() or DatasetStore(out).info()["rows"] < 10:
        assert first.poll() is None, first.stderr.read()
        assert time.monotonic() < deadline, "the first generation never started"
        time.sleep(0.05)
    second = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=120)
    assert second.returncode == 2, second.stderr
    assert "another process is growing the adaptive design" in second.stderr
    assert len(second.stderr.strip().splitlines()) == 1
    first.send_signal(signal.SIGKILL)
    first.wait(timeout=10)
    stored = DatasetStore(out).info()["rows"]
    done = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["complete"] and summary["total_rows"] == 80 and summary["already_present"] >= stored
