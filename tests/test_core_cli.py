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
