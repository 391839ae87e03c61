"""Targets for `invphys invert`: every input form, and every bad input as one line with exit 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from test_inverter_support import toy_run
from typer.testing import CliRunner

NAMES = ("peak_abs", "final_abs", "log_decay", "crossings_per_s", "final_damage")
GOOD = {"peak_abs": 0.9, "final_abs": 0.2, "log_decay": -0.5, "crossings_per_s": 1.0, "final_damage": 0.1}


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return toy_run(tmp_path_factory.getbasetemp()) / "inverter"


def invoke(*args: str):
    from invphys.cli import app

    return CliRunner().invoke(app, list(args))


def _one_line_error(res, *needles: str) -> None:
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), res.output
    for n in needles:
        assert n in lines[0], lines[0]


# -- parsing ------------------------------------------------------------------------------------------
def test_file_shapes(tmp_path) -> None:
    from invphys.core.user_targets import read_target_file

    (tmp_path / "one.json").write_text(json.dumps(GOOD))
    (tmp_path / "many.json").write_text(json.dumps({"targets": [{"id": "a", **GOOD}, {"id": "b", **GOOD}]}))
    (tmp_path / "list.yaml").write_text("- " + json.dumps(GOOD) + "\n- " + json.dumps({**GOOD, "peak_abs": 0.5}))
    (tmp_path / "t.csv").write_text("id," + ",".join(NAMES) + "\nfirm,0.9,0.2,-0.5,1,0.1\nsoft,0.5,,-0.4,2,0.3\n")
    assert read_target_file(tmp_path / "one.json", NAMES).values.tolist() == [list(GOOD.values())]
    many = read_target_file(tmp_path / "many.json", NAMES)
    assert many.labels == ["a", "b"] and len(many) == 2
    assert read_target_file(tmp_path / "list.yaml", NAMES).values[1, 0] == 0.5
    csv = read_target_file(tmp_path / "t.csv", NAMES, partial=True)
    assert csv.labels == ["firm", "soft"] and csv.mask[1].tolist() == [True, False, True, True, True]
    with pytest.raises(Exception, match=r"t.csv #2: missing feature\(s\) final_abs"):
        read_target_file(tmp_path / "t.csv", NAMES)


def test_array_and_assignments() -> None:
    from invphys.core.user_targets import TargetError, from_array, parse_assignments

    assert from_array(list(GOOD.values()), NAMES).values.shape == (1, 5)
    assert from_array(np.ones((3, 5)), NAMES).labels == ["t0", "t1", "t2"]
    t = parse_assignments([f"{k}={v}" for k, v in GOOD.items()], NAMES)
    assert t.values[0].tolist() == list(GOOD.values())
    for bad, msg in ((["peak_abs"], "expected name=value"), (["peak_abs=1", "peak_abs=2"], "given twice"),
                     (["peak_abs=x"], "not a number"), (["peak_abs=nan"], "not finite")):
        with pytest.raises(TargetError, match=msg):
            parse_assignments(bad, NAMES, partial=True)


# -- the CLI, one input form at a time ----------------------------------------------------------------
def test_feature_items(bundle) -> None:
    res = invoke("invert", str(bundle), *[a for k, v in GOOD.items() for a in ("--feature", f"{k}={v}")], "--json")
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)["results"]
    assert len(out) == 1
    cand = out[0]["candidates"][0]
    assert list(cand["parameters"]) == ["k", "c", "m"] and cand["parameters"]["k"]["unit"] == "N/m"
    assert cand["features"]["peak_abs"]["target"] == 0.9 and 0 <= cand["r_surrogate"] <= 1


@pytest.mark.parametrize("name", ["t.json", "t.yaml", "t.csv"])
def test_target_files(bundle, tmp_path, name) -> None:
    path = tmp_path / name
    rows = [{"id": "one", **GOOD}, {"id": "two", **GOOD, "peak_abs": 0.5}]
    if name.endswith(".csv"):
        path.write_text("id," + ",".join(NAMES) + "\n" + "\n".join(
            ",".join(str(r[k]) for k in ("id", *NAMES)) for r in rows) + "\n")
    else:
        path.write_text(json.dumps({"targets": rows}))  # JSON is YAML too
    res = invoke("invert", str(bundle), "--target", str(path), "--json")
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)["results"]
    assert [r["target"] for r in out] == ["one", "two"]
    assert out[1]["candidates"][0]["features"]["peak_abs"]["target"] == 0.5


def test_spreadsheet_csv_with_a_bom_is_answered(bundle, tmp_path) -> None:
    """A CSV saved by a spreadsheet starts with a UTF-8 BOM: its first column is still a feature (it was
    "unknown feature '\\ufeffpeak_abs'")."""
    path = tmp_path / "excel.csv"
    path.write_bytes(b"\xef\xbb\xbf" + (",".join(NAMES) + "\r\n" + ",".join(str(GOOD[k]) for k in NAMES)
                                          + "\r\n").encode())
    res = invoke("invert", str(bundle), "--target", str(path), "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["results"][0]["candidates"][0]["features"]["peak_abs"]["target"] == 0.9


@pytest.mark.parametrize(("name", "text", "needle"), [
    ("dup.csv", ",".join(NAMES) + ",peak_abs\n0.9,0.2,-0.5,1,0.1,0.3\n", "columns 1 and 6 are both named 'peak_abs'"),
    ("dup.json", '{"peak_abs": 0.9,\n "final_abs": 0.2,\n "peak_abs": 0.5}', "key 'peak_abs' appears twice in one "
     "object (lines 1 and 3)"),
    ("dup.yaml", "peak_abs: 0.9\nfinal_abs: 0.2\npeak_abs: 0.5\n", "key 'peak_abs' appears twice in one mapping "
     "(lines 1 and 3)"),
    ("big.yaml", "peak_abs: " + "9" * 400 + "\n", "too large for a number"),
    ("big.json", '{"peak_abs": ' + "9" * 400 + "}", "too large for a number"),
], ids=["dup-csv", "dup-json", "dup-yaml", "int400-yaml", "int400-json"])
def test_duplicates_and_huge_integers_are_refused(bundle, tmp_path, name, text, needle) -> None:
    """Last-wins duplicates were accepted silently; 400-digit integers were an internal error."""
    path = tmp_path / name
    path.write_text(text)
    _one_line_error(invoke("invert", str(bundle), "--target", str(path), "--partial"), needle)
    assert path.read_text() == text


def test_observed_trajectory(bundle, tmp_path) -> None:
    from test_dataset_toy import ToyFeatures, ToyOscillator

    traj = ToyOscillator().simulate(np.array([[30.0, 0.1, 1.0]]))[0].trajectory
    path = tmp_path / "run1" / "trajectory.npz"
    path.parent.mkdir()
    np.savez_compressed(path, positions=traj.positions, damage=traj.damage, labels=traj.labels,
                        frame_indices=traj.frame_indices, fps=np.float64(traj.fps))
    expected = ToyFeatures().extract(traj)
    for arg in (path, path.parent):  # a file or a run directory
        res = invoke("invert", str(bundle), "--observed", str(arg), "--json")
        assert res.exit_code == 0, res.output
        feats = json.loads(res.stdout)["results"][0]["candidates"][0]["features"]
        assert [feats[n]["target"] for n in NAMES] == pytest.approx(expected)
    # the framework's trajectory file, as `invphys simulate` writes it (header, optional time series)
    from invphys.core.results import TimeSeries
    from invphys.core.trajectory_io import read_header, save_trajectory

    traj.series["x"] = TimeSeries(times=np.arange(3.0), values=np.zeros(3), unit="m")
    v1 = save_trajectory(traj, tmp_path / "v1.npz", simulator={"simulator": "toy"})
    assert read_header(v1)["format"] == "invphys.trajectory"
    res = invoke("invert", str(bundle), "--observed", str(v1), "--json")
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)["results"][0]
    assert out["target"] == "v1"
    assert [out["candidates"][0]["features"][n]["target"] for n in NAMES] == pytest.approx(expected)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    _one_line_error(invoke("invert", str(bundle), "--observed", str(tmp_path / "junk.npz")), "cannot read trajectory")


def test_partial_targets_need_the_flag(bundle) -> None:
    _one_line_error(invoke("invert", str(bundle), "--feature", "peak_abs=0.9"), "missing feature(s)", "partial")
    res = invoke("invert", str(bundle), "--feature", "peak_abs=0.9", "--partial", "--json")
    assert res.exit_code == 0, res.output
    r = json.loads(res.stdout)["results"][0]
    assert r["partial"] and r["candidates"][0]["features"]["final_abs"]["used"] is False


def test_far_target_is_answered_with_a_warning(bundle) -> None:
    res = invoke("invert", str(bundle), *[a for k, v in {**GOOD, "peak_abs": 1e4}.items()
                                          for a in ("--feature", f"{k}={v}")], "--json")
    assert res.exit_code == 0
    out = json.loads(res.stdout)["results"][0]
    assert any("peak_abs = 1e+04" in w and "outside the training data" in w for w in out["warnings"])


# -- bad input: one line, exit 2 ----------------------------------------------------------------------
def test_bad_inputs(bundle, tmp_path) -> None:
    feats = [a for k, v in GOOD.items() for a in ("--feature", f"{k}={v}")]
    _one_line_error(invoke("invert", str(bundle), *feats, "--feature", "peak_ab=1"), "'peak_ab'",
                    "Did you mean 'peak_abs'?")
    _one_line_error(invoke("invert", str(bundle), "--feature", "peak_abs=inf", "--partial"), "not finite")
    _one_line_error(invoke("invert", str(bundle)), "give a target")
    (tmp_path / "short.csv").write_text(",".join(NAMES) + "\n1,2,3\n")
    _one_line_error(invoke("invert", str(bundle), "--target", str(tmp_path / "short.csv")), "fewer values")
    (tmp_path / "bad.json").write_text("{oops")
    _one_line_error(invoke("invert", str(bundle), "--target", str(tmp_path / "bad.json")), "not valid JSON")
    _one_line_error(invoke("invert", str(bundle), "--target", str(tmp_path / "absent.json")), "cannot read")
    (tmp_path / "t.txt").write_text("x")
    _one_line_error(invoke("invert", str(bundle), "--target", str(tmp_path / "t.txt")), "unsupported type")
    (tmp_path / "nan.json").write_text('{"peak_abs": NaN}')
    _one_line_error(invoke("invert", str(bundle), "--target", str(tmp_path / "nan.json"), "--partial"), "not finite")
    _one_line_error(invoke("invert", str(tmp_path), *feats), "not an inverter bundle")
    _one_line_error(invoke("invert", str(bundle), *feats, "--method", "gc_flw"), "Did you mean 'gc_flow'?")


def test_wrong_count_through_the_api(bundle) -> None:
    from invphys.core.user_targets import TargetError
    from invphys.inverter import load_inverter

    inv = load_inverter(bundle)
    with pytest.raises(TargetError, match="expected 5 feature values"):
        inv.invert([1.0, 2.0, 3.0])


def test_real_process_exit_codes(bundle) -> None:
    tests = os.path.dirname(os.path.abspath(__file__))  # the toy simulator's module
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "invphys.cli", "invert", str(bundle), "--feature", "peak_abss=1"]
    bad = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 2 and bad.stdout == ""
    assert len(bad.stderr.strip().splitlines()) == 1 and "Did you mean 'peak_abs'" in bad.stderr


# -- the spec's own targets ---------------------------------------------------------------------------
USER_SPEC = """
name: user-targets
seed: 1
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 80, batch_size: 40}
surrogate: {type: mlp, hidden: [16, 16, 8], max_epochs: 10, dropout: 0.0}
optimizers:
  cma: {type: cma_es, budget: 40}
stages: [dataset, train, invert]
"""


def _run_user_spec(tmp_path, targets: dict):
    import io

    import yaml
    from rich.console import Console

    from invphys.core.spec import ExperimentSpec, validate_spec
    from invphys.pipeline.runner import run_spec

    data = yaml.safe_load(USER_SPEC)
    data["targets"] = targets
    if "evaluation" in ExperimentSpec.model_fields:
        data["evaluation"] = {"baselines": {}}
    out = tmp_path / "run"
    run_spec(validate_spec(data), out, progress=False, console=Console(file=io.StringIO()))
    return json.loads((out / "invert" / "targets.json").read_text()), json.loads(
        (out / "invert" / "results.json").read_text())


def test_spec_values_and_file_targets(tmp_path) -> None:
    from invphys.core.errors import SpecError
    from invphys.core.spec import validate_spec

    targets, rows = _run_user_spec(tmp_path / "a", {"values": [{"id": "lively", **GOOD}], "validate": 0})
    assert targets["labels"] == ["lively"] and targets["features"] == [list(GOOD.values())]
    assert targets["ground_truth"] is False and [r["dataset_row"] for r in rows] == [None]
    csv = tmp_path / "mine.csv"
    csv.write_text(",".join(NAMES) + "\n0.9,0.2,-0.5,1,0.1\n0.5,0.1,-0.2,2,0.3\n")
    targets, rows = _run_user_spec(tmp_path / "b", {"file": str(csv), "validate": 0})
    assert len(targets["features"]) == 2 and len(rows) == 2
    with pytest.raises(Exception, match="unknown feature 'peak_ab'"):
        _run_user_spec(tmp_path / "c", {"values": [{**GOOD, "peak_ab": 1.0}], "validate": 0})
    import yaml

    bad = {**yaml.safe_load(USER_SPEC), "targets": {"values": [GOOD], "file": "x.csv"}}
    with pytest.raises(SpecError, match="not both"):
        validate_spec(bad)


def test_spec_targets_with_noise_are_refused_before_running(tmp_path) -> None:
    """A spec's invert stage answers exact targets: a per-feature std (which `invphys invert` uses) is one
    located error at validation, for values and for a file, instead of being dropped silently."""
    import yaml

    from invphys.core.errors import SpecError
    from invphys.core.spec import validate_spec

    name = NAMES[0]
    noisy = {**yaml.safe_load(USER_SPEC), "targets": {"values": [{**GOOD, f"{name}_std": 0.1}]}}
    with pytest.raises(SpecError, match="noisy observation"):
        validate_spec(noisy)
    csv = tmp_path / "noisy.csv"
    csv.write_text(",".join(NAMES) + f",{name}_std\n0.9,0.2,-0.5,1,0.1,0.05\n")
    with pytest.raises(SpecError, match="noisy observation"):
        validate_spec({**yaml.safe_load(USER_SPEC), "targets": {"file": str(csv)}})
    exact = {**yaml.safe_load(USER_SPEC), "targets": {"values": [{**GOOD, f"{name}_std": 0}]}}
    validate_spec(exact)  # a zero std is an exact target
