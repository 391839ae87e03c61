"""The validate stage is resumable: each run is appended to disk as it finishes, a run killed with
SIGKILL mid-validate and started again simulates only what is missing and changes no finished row;
and user targets without ground truth (targets.values) validate and report with render and the
noise floor left on; the renders' target runs are the noise floor's runs (simulated once)."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import yaml
from test_dataset_toy import SIM, ToyOscillator

TESTS = str(Path(__file__).resolve().parent)

SPEC = f"""
name: validate-resume
seed: 1
simulator: {{type: "{SIM}"}}
dataset: {{n: 120, batch_size: 40}}
surrogate: {{type: mlp, hidden: [16, 16, 8], max_epochs: 20, patience: 5}}
optimizers:
  cma: {{type: cma_es, budget: 40}}
targets: {{n: 6, validate: 6, selection: farthest_point+random}}
evaluation:
  baselines:
    nearest_neighbour: {{type: nearest_neighbour}}
  methods:
    sil: {{start: nearest_neighbour, evaluator: simulator, budget: 6, popsize: 3}}
  best_of:
    best: [cma, nearest_neighbour]
validator: {{type: simulator, batch_size: 2, overrides: {{sleep_s: SLEEP}}}}
report: {{render: false}}
"""


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")]),
            "INVPHYS_DISABLE_PLUGIN_AUTOLOAD": "1"}


def _run(spec_text: str, out: Path, stages: list[str]) -> dict:
    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    return run_spec(parse_spec(spec_text), out, stages=stages, progress=False, console=Console(file=io.StringIO()))


def _lines(path: Path) -> list[bytes]:
    return path.read_bytes().splitlines(keepends=True) if path.is_file() else []


def test_sigkill_mid_validate_then_resume_keeps_finished_rows(tmp_path) -> None:
    spec_text = SPEC.replace("SLEEP", "0.4")
    spec = tmp_path / "spec.yaml"
    spec.write_text(spec_text)
    out = tmp_path / "run"
    _run(spec_text, out, ["dataset", "train", "invert"])
    memo = out / "validate" / "simulated.jsonl"
    cmd = [sys.executable, "-m", "invphys.cli", "run", str(spec), "--out", str(out), "--stage", "validate",
           "--no-progress"]
    proc = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while len(_lines(memo)) < 8:  # the in-loop generations and a first validation batch are on disk
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "no rows appeared"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "validate" / "validation.json").exists()
    before = _lines(memo)
    # a torn line, as a kill in the middle of a write leaves it, is cut off on resume
    with open(memo, "ab") as fh:
        fh.write(b'{"key": "torn", "feat')

    done = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    after = _lines(memo)
    assert after[:len(before)] == before  # finished rows never change
    keys = [json.loads(line)["key"] for line in after]
    assert len(keys) == len(set(keys)) and len(after) > len(before)  # each vector simulated once
    rows = json.loads((out / "validate" / "validation.json").read_text())
    assert len({r["optimizer"] for r in rows}) >= 3 and all(np.isfinite(r["r_actual"]) for r in rows)

    # an uninterrupted run gives the same validated rows (resuming changes nothing)
    ref_rows = _reference_rows(spec_text, out, tmp_path)
    key = lambda r: (r["optimizer"], r["target_index"])  # noqa: E731
    got = {key(r): r["r_actual"] for r in rows}
    assert got == {key(r): r["r_actual"] for r in ref_rows}


def _reference_rows(spec_text: str, out: Path, tmp_path: Path) -> list[dict]:
    """Validate the same invert results again from scratch (a copy of the run without the memo)."""
    import shutil

    ref = tmp_path / "ref_copy"
    shutil.copytree(out, ref, ignore=shutil.ignore_patterns("validate", "report"))
    _run(spec_text, ref, ["validate"])
    assert json.loads((ref / "validate" / "DONE.json").read_text())
    return json.loads((ref / "validate" / "validation.json").read_text())


def test_user_targets_without_ground_truth_validate_and_report(tmp_path) -> None:
    from test_dataset_toy import FEATURES  # noqa: F401  (the toy's feature extractor is registered)

    spec_text = SPEC.replace("SLEEP", "0.0")
    base = tmp_path / "base"
    _run(spec_text, base, ["dataset"])
    from invphys.core.dataset import DatasetStore

    arr = DatasetStore(base / "dataset" / "store").arrays()
    values = [dict(zip(arr.feature_names, map(float, arr.y[i]), strict=True)) for i in (3, 50)]
    data = yaml.safe_load(spec_text)
    data["targets"] = {"values": [{"id": "a", **values[0]}, {"id": "b", **values[1]}], "validate": 2}
    data["report"] = {"render": True}
    text = yaml.safe_dump(data)
    out = tmp_path / "run"
    summaries = _run(text, out, ["dataset", "train", "invert", "validate", "report"])
    rows = json.loads((out / "validate" / "validation.json").read_text())
    labels = {r["optimizer"] for r in rows}
    assert labels == {"cma", "nearest_neighbour", "sil", "best"}  # no noise floor without a ground truth
    assert len(rows) == 8 and all(np.isfinite(r["r_actual"]) for r in rows)
    by = {(r["optimizer"], r["target_index"]): r for r in rows}
    for k in (0, 1):  # the simulator-selected answer is the better validated candidate, at both their costs
        best = by[("best", k)]
        assert best["r_actual"] == max(by[("cma", k)]["r_actual"], by[("nearest_neighbour", k)]["r_actual"])
        assert best["evaluations"] == by[("cma", k)]["evaluations"] and best["simulator_runs"] in (1, 2)
    assert summaries["validate"]["renders"] == []
    rep = json.loads((out / "report" / "report.json").read_text())
    assert rep["optimizers"]["sil"]["n_validated"] == 2
    assert rep["optimizers"]["sil"]["r_actual_mean"] == pytest.approx(
        np.mean([r["r_actual"] for r in rows if r["optimizer"] == "sil"]))


def test_memo_survives_a_new_batch_size_but_not_another_simulator(tmp_path) -> None:
    """Batching is no part of a run's identity (as in dataset stores); the simulator's settings are."""
    from test_dataset_toy import ToyFeatures, ToyOscillator

    from invphys.core.dataset import RunIdentity
    from invphys.pipeline.runner import fingerprint
    from invphys.pipeline.sim_checkpoint import SimCheckpoint
    from invphys.plugins.validators.simulator import SimulatorValidator

    theta = np.random.default_rng(0).uniform(size=(5, 3))
    calls = []

    def memo(sim, batch):
        v = SimulatorValidator(batch_size=batch)
        ck = SimCheckpoint(tmp_path / "m.jsonl", fingerprint(RunIdentity.of(sim).to_dict()))

        def simulate(th, **kw):
            calls.append(len(th))
            return v.simulate_features(th, sim, ToyFeatures(), **kw)
        return ck.simulate(theta, simulate, batch, 5)

    a = memo(ToyOscillator(), 2)
    assert calls == [2, 2, 1]
    b = memo(ToyOscillator(), 4)  # another batch size: everything reused, bit for bit
    assert calls == [2, 2, 1] and np.array_equal(a.features, b.features, equal_nan=True)
    memo(ToyOscillator(substeps=3), 4)  # another simulator config: simulated again
    assert calls == [2, 2, 1, 4, 1]


def test_runs_finished_before_a_stop_inside_a_batch_are_kept(tmp_path) -> None:
    """A call stopped in the middle of a validator batch keeps the runs that finished (each is appended as
    the simulator reports it); the next call simulates only the rest and gives the uninterrupted result."""
    from test_dataset_toy import ToyFeatures, ToyOscillator

    from invphys.core.dataset import RunIdentity
    from invphys.pipeline.runner import fingerprint
    from invphys.pipeline.sim_checkpoint import SimCheckpoint
    from invphys.plugins.validators.simulator import SimulatorValidator

    theta = np.random.default_rng(1).uniform(size=(6, 3))
    sim, v = ToyOscillator(), SimulatorValidator(batch_size=6)
    ident = fingerprint(RunIdentity.of(sim).to_dict())

    class Stop(Exception):
        pass

    def stop_after_two(th, on_run=None, **kw):
        def run(i):
            if on_run is not None:
                on_run(i)
            if i == 1:
                raise Stop  # a kill after the second run of the only batch finished
        return v.simulate_features(th, sim, ToyFeatures(), on_run=run, **kw)

    path = tmp_path / "memo.jsonl"
    with pytest.raises(Stop):
        SimCheckpoint(path, ident).simulate(theta, stop_after_two, 6, 5)
    assert len(_lines(path)) == 2                  # both finished runs are on disk, nothing else
    kept = _lines(path)
    calls = []

    def simulate(th, **kw):
        calls.append(len(th))
        return v.simulate_features(th, sim, ToyFeatures(), **kw)

    again = SimCheckpoint(path, ident)
    resumed = again.simulate(theta, simulate, 6, 5)
    assert calls == [4] and again.reused == 2     # only the four missing runs
    assert _lines(path)[:2] == kept                # finished rows unchanged
    whole = SimCheckpoint(tmp_path / "whole.jsonl", ident).simulate(theta, simulate, 6, 5)
    np.testing.assert_array_equal(resumed.features, whole.features)


def test_memo_is_found_whatever_the_spec_calls_the_feature_extractor(tmp_path) -> None:
    """The memo keys runs by the resolved extractor, not the spec's wording: a run folder validated with
    the simulator's default extractor replays every run when the spec names the same extractor by its
    module path (as GPU-machine specs do without installed entry points); a changed extractor config
    does not replay."""
    spec_text = SPEC.replace("SLEEP", "0.0")
    out = tmp_path / "run"
    _run(spec_text, out, ["dataset", "train", "invert", "validate"])
    memo = out / "validate" / "simulated.jsonl"
    before = _lines(memo)
    assert len(before) > 6
    named = spec_text.replace("dataset: {", 'features: {type: "test_dataset_toy:ToyFeatures"}\ndataset: {', 1)
    summary = _run(named, out, ["validate"])
    assert _lines(memo) == before  # nothing simulated, nothing appended
    assert summary["validate"]["failed"] == 0


def test_checkpoint_finds_records_of_a_legacy_identity(tmp_path) -> None:
    """Records written under an earlier identity are replayed when it is given as ``legacy``; runs it lacks
    are simulated and appended under the current identity."""
    from invphys.pipeline.sim_checkpoint import SimCheckpoint
    from invphys.plugins.validators.simulator import SimulatedFeatures

    calls: list[int] = []

    def simulate(theta, keep_trajectories=False, on_record=None, on_run=None):
        calls.append(len(theta))
        feats = np.column_stack([theta.sum(axis=1), theta[:, 0]])
        return SimulatedFeatures(feats, [None] * len(theta), [None] * len(theta), [None] * len(theta))

    theta = np.random.default_rng(0).random((5, 3))
    path = tmp_path / "memo.jsonl"
    old = SimCheckpoint(path, "identity-v1")
    first = old.simulate(theta[:3], simulate, 2, 2)
    assert calls == [2, 1]
    new = SimCheckpoint(path, "identity-v2", legacy=["identity-v1"])
    got = new.simulate(theta, simulate, 8, 2)
    assert calls == [2, 1, 2]  # only the two rows the old memo lacks
    np.testing.assert_array_equal(got.features[:3], first.features)
    assert new.reused == 3 and new.simulated == 2
    again = SimCheckpoint(path, "identity-v2")  # without the legacy identity the old rows are not found
    again.simulate(theta, simulate, 8, 2)
    assert calls[-1] == 3


def test_renders_draw_the_noise_floor_runs_without_simulating_the_targets_again(tmp_path) -> None:
    """With render and the noise floor on, each target's true parameters are simulated once: the noise
    floor's run is the target run the renders draw (the demo's validation was a run per target longer)."""
    data = yaml.safe_load(SPEC.replace("SLEEP", "0.0"))
    data["simulator"] = {"type": "test_validate_resume:CountingOscillator"}
    data["targets"] = {"n": 2, "validate": 2}
    data["evaluation"] = {"baselines": {"nearest_neighbour": {"type": "nearest_neighbour"}}}
    data["report"] = {"render": True}
    text = yaml.safe_dump(data)
    out = tmp_path / "run"
    _run(text, out, ["dataset", "train", "invert"])
    CountingOscillator.rows.clear()
    summary = _run(text, out, ["validate", "report"])["validate"]
    rows = json.loads((out / "validate" / "validation.json").read_text())
    assert {r["optimizer"] for r in rows} == {"cma", "nearest_neighbour", "noise_floor"} and len(rows) == 6
    assert len(CountingOscillator.rows) == summary["simulated"]  # no run beside the validated vectors
    truth = {tuple(r["theta"]) for r in rows if r["optimizer"] == "noise_floor"}
    space = CountingOscillator().parameter_space()
    simulated = [tuple(np.round(p, 9)) for p in CountingOscillator.rows]
    for theta in truth:
        assert simulated.count(tuple(np.round(space.denormalize(np.asarray(theta)), 9))) == 1
    assert sorted(r["target_index"] for r in summary["renders"]) == [0, 1]
    for k in (0, 1):
        assert (out / "validate" / "renders" / f"t{k:02d}_target.npz").is_file()
        assert (out / "report" / "renders" / f"t{k:02d}.png").is_file()


class CountingOscillator(ToyOscillator):
    """The toy oscillator, recording every parameter row it simulates in this process."""

    name = "counting_oscillator"
    rows: ClassVar[list[np.ndarray]] = []

    def simulate(self, params, on_result=None):
        CountingOscillator.rows.extend(np.atleast_2d(np.asarray(params, dtype=np.float64)))
        return super().simulate(params, on_result)
