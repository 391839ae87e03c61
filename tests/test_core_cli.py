"""The CLI: exit codes, --json output, did-you-mean and field paths, no tracebacks on bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from core_plugins import LineSimulator, RandomSearch
from typer.testing import CliRunner

from invphys import registry
from invphys.cli import app

runner = CliRunner()

SPEC = """\
name: cli-demo
simulator: {type: test_line}
optimizers:
  rs: {type: test_random_search, sigma0: 0.5}
stages: [dataset]
"""


@pytest.fixture(autouse=True)
def plugins():
    with registry.registered(LineSimulator, RandomSearch):
        yield


def invoke(*args: str):
    return runner.invoke(app, list(args))


def test_validate_good_spec_json(tmp_path):
    path = tmp_path / "spec.yaml"
    path.write_text(SPEC)
    result = invoke("validate", str(path), "--json")
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["valid"] and data["name"] == "cli-demo"
    assert {"path": "optimizers.rs", "kind": "optimizer", "type": "test_random_search"} in data["plugins"]


def test_validate_misspelled_plugin_exit_2_did_you_mean(tmp_path):
    path = tmp_path / "spec.yaml"
    path.write_text(SPEC.replace("test_random_search", "test_random_serch"))
    result = invoke("validate", str(path))
    assert result.exit_code == 2
    assert "No optimizer named 'test_random_serch'. Did you mean 'test_random_search'?" in result.output
    assert "Traceback" not in result.output


def test_validate_bad_field_names_path(tmp_path):
    path = tmp_path / "spec.yaml"
    path.write_text(SPEC.replace("sigma0: 0.5", "sigma0: 0"))
    result = invoke("validate", str(path))
    assert result.exit_code == 2
    assert "optimizers.rs.sigma0 (line 4): must be > 0" in result.output


def test_debug_flag_shows_traceback(tmp_path):
    path = tmp_path / "missing.yaml"
    result = invoke("--debug", "validate", str(path))
    assert result.exit_code != 0 and result.exception is not None


def test_plugins_json_lists_registered_with_distribution():
    result = invoke("plugins", "--json")
    assert result.exit_code == 0
    rows = json.loads(result.stdout)
    row = next(r for r in rows if r["name"] == "test_random_search")
    assert row == {"kind": "optimizer", "name": "test_random_search", "distribution": "<test>", "version": "",
                   "class": "core_plugins:RandomSearch"}


def test_unknown_kind_is_exit_2():
    result = invoke("plugins", "--kind", "optimiser")
    assert result.exit_code == 2 and "Did you mean 'optimizer'" in result.output


def test_schema_is_json_with_plugin_blocks():
    result = invoke("schema")
    assert result.exit_code == 0
    schema = json.loads(result.stdout)
    assert "optimizer_block" in schema["$defs"]


def test_real_process_exit_code_and_no_traceback(tmp_path):
    path = tmp_path / "spec.yaml"
    path.write_text("name: x\nsimulator: {type: core_plugins:NoSuchThing}\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.path.dirname(__file__), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", "validate", str(path)], capture_output=True,
                          text=True, env=env)
    assert proc.returncode == 2
    assert "simulator.type (line 2): module 'core_plugins' has no attribute 'NoSuchThing'" in proc.stderr
    assert "Traceback" not in proc.stderr


# -- validate knows what run knows (issues 47, 50) ------------------------------------------------------
TOY = """\
name: toy
simulator: {type: "test_dataset_toy:ToyOscillator", n_frames: 10}
dataset: {n: 8, batch_size: 4}
surrogate: {type: mlp, max_epochs: 2, hidden: [4, 4, 4]}
optimizers:
  cma: {type: cma_es, space: raw, budget: 20}
stages: [dataset, train, invert]
"""


@pytest.mark.parametrize("targets, expect", [
    ("targets: {values: [{peak_abs: 1.0, final_abs: 0.1, log_decay: -1, crossings_per_s: 2, final_damag: 0}]}",
     "targets.values (line 8): unknown feature 'final_damag'. Did you mean 'final_damage'?"),
    ("targets: {file: no_such_targets.csv}", "targets.file (line 8): 'no_such_targets.csv' is absent"),
    ("targets: {file: targets.csv}", "targets.file (line 8): targets.csv: unknown feature 'peak'."),
])
def test_validate_reads_the_targets_as_run_would(targets, expect, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "targets.csv").write_text("peak,final_abs\n1,2\n")
    (tmp_path / "spec.yaml").write_text(TOY + targets + "\n")
    for args in (["validate", "spec.yaml"], ["run", "spec.yaml", "--out", "run"]):
        result = invoke(*args)
        assert result.exit_code == 2 and expect in result.output, result.output
    assert not (tmp_path / "run").exists()  # refused before any simulation or training


def test_validate_json_always_json_with_every_problem_at_once(tmp_path) -> None:
    path = tmp_path / "spec.yaml"
    path.write_text("name: t\nseed: -1\nsimulator: {type: \"test_dataset_toy:ToyOscillator\", n_frames: 0}\n"
                    "dataset: {n: 0}\noptimizers:\n  cma: {type: cma_es, budget: 0}\n")
    result = invoke("validate", str(path), "--json")
    assert result.exit_code == 2
    data = json.loads(result.stdout)
    assert data["ok"] is False and data["valid"] is False
    # the shape's problems and the plugin blocks' problems together, each located (before: only the first two)
    assert [(e["path"], e["line"]) for e in data["errors"]] == [
        ("seed", 2), ("simulator.n_frames", 3), ("dataset.n", 4), ("optimizers.cma.budget", 6)]
    assert data["errors"][1]["message"] == "must be >= 2"
    missing = invoke("validate", str(tmp_path / "missing.yaml"), "--json")
    assert missing.exit_code == 2 and json.loads(missing.stdout)["errors"][0]["path"] is None
    good = tmp_path / "good.yaml"
    good.write_text(SPEC)
    ok = json.loads(invoke("validate", str(good), "--json").stdout)
    assert ok["ok"] is True and ok["errors"] == []


def test_schema_out_a_directory_or_under_a_file_is_one_line(tmp_path) -> None:
    (tmp_path / "f").write_text("x")
    for target, expect in ((tmp_path, "is a directory"), (tmp_path / "f" / "s.json", "which is a file")):
        result = invoke("schema", "--out", str(target))
        assert result.exit_code == 2 and expect in result.output and len(result.output.strip().splitlines()) == 1
    written = tmp_path / "s.json"
    assert invoke("schema", "--out", str(written)).exit_code == 0 and json.loads(written.read_text())["$defs"]


def test_dataset_verify_of_a_damaged_store_exits_2_with_an_error_line(tmp_path) -> None:
    from invphys.data.generate import generate_dataset

    store = tmp_path / "store"
    generate_dataset(store, {"type": "test_dataset_toy:ToyOscillator", "n_frames": 10}, n=8, batch_size=4,
                     progress=False)
    assert invoke("dataset", "verify", str(store)).exit_code == 0
    sorted(store.glob("part-*.parquet"))[0].unlink()
    result = invoke("dataset", "verify", str(store), "--json")
    assert result.exit_code == 2  # damage found is the user's data, not a bug (was 1)
    assert json.loads(result.stdout)["problems"][0]["kind"] == "missing"
    assert f"error: {store}: 1 problem found" in result.stderr
