"""CLI manners (issue 10): one line for unexpected errors, --version, -h, plain flags, unclipped pipes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

import invphys
from invphys.cli import app, main
from invphys.cli.common import set_debug

runner = CliRunner()


def invphys_cli(*args: str) -> subprocess.CompletedProcess[str]:
    """The real console entry point in a child process, its output piped (not a terminal)."""
    return subprocess.run([sys.executable, "-m", "invphys.cli", *args], capture_output=True, text=True,
                          timeout=120)


@pytest.fixture
def broken_validate(monkeypatch):
    """Make `invphys validate` hit a bug (not a user error) deep inside."""
    import invphys.core.spec as spec_module

    def explode(path):
        raise KeyError("a field nobody expected")

    monkeypatch.setattr(spec_module, "load_spec", explode)
    yield
    set_debug(False)


def test_unexpected_exception_is_one_line_exit_1(broken_validate, tmp_path) -> None:
    result = runner.invoke(app, ["validate", str(tmp_path / "x.yaml")])
    assert result.exit_code == 1
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines == ["internal error: KeyError: 'a field nobody expected' (run with --debug for the traceback)"]


def test_debug_shows_the_traceback(broken_validate, tmp_path) -> None:
    result = runner.invoke(app, ["--debug", "validate", str(tmp_path / "x.yaml")])
    assert result.exit_code != 0
    assert isinstance(result.exception, KeyError)


def test_main_turns_escaping_exceptions_into_exit_codes(monkeypatch, capsys) -> None:
    from invphys.core.errors import InvphysError

    def fail(exc: BaseException):
        def app_stub() -> None:
            raise exc
        return app_stub

    monkeypatch.setattr("invphys.cli.app", fail(InvphysError("bad input")))
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 2
    monkeypatch.setattr("invphys.cli.app", fail(RuntimeError("boom")))
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 1
    err = capsys.readouterr().err
    assert "error: bad input" in err and "internal error: RuntimeError: boom" in err


def test_user_errors_still_exit_2_without_traceback(tmp_path) -> None:
    missing = tmp_path / "missing.yaml"
    result = invphys_cli("validate", str(missing))
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_version_and_short_help() -> None:
    version = invphys_cli("--version")
    assert version.returncode == 0 and version.stdout.strip() == f"invphys {invphys.__version__}"
    short, long = invphys_cli("run", "-h"), invphys_cli("run", "--help")
    assert short.returncode == 0 and short.stdout == long.stdout
    assert "--no-progress" in short.stdout and "<bool>" not in short.stdout


def test_piped_tables_keep_full_names() -> None:
    result = invphys_cli("plugins")
    assert result.returncode == 0, result.stderr
    assert "…" not in result.stdout
    (row,) = [line for line in result.stdout.splitlines() if " cma_es " in line]
    assert "invphys.plugins.optimizers.cma_es:CMAES" in row


# -- Ctrl-C and -q/-qq tell the truth (issue 50) ---------------------------------------------------------
TESTS = str(Path(__file__).resolve().parent)
SLOW = """\
name: slow
simulator: {type: "test_dataset_toy:ToyOscillator", n_frames: 10, sleep_s: 0.4}
dataset: {n: 40, batch_size: 2}
stages: [dataset]
"""
TINY = """\
name: tiny
simulator: {type: "test_dataset_toy:ToyOscillator", n_frames: 10}
dataset: {n: 8, batch_size: 4}
stages: [dataset]
"""


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "INVPHYS_DEBUG"}  # an in-process --debug test sets it
    return {**env, "PYTHONPATH": os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")])}


def test_out_naming_a_file_is_a_user_error(tmp_path) -> None:
    taken = tmp_path / "taken"
    taken.write_text("precious")
    result = subprocess.run([sys.executable, "-m", "invphys.cli", "simulate", "--simulator", "test_dataset_toy:ToyOscillator",
                             "--out", str(taken)], env=_env(), capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == f"error: --out '{taken}' is a file; name a new or existing directory"
    assert taken.read_text() == "precious"


@pytest.mark.parametrize("command", [["run", "spec.yaml", "--out", "run"],
                                     ["dataset", "generate", "spec.yaml", "--out", "ds"]])
def test_ctrl_c_prints_interrupted_and_exits_130(command, tmp_path) -> None:
    """A real process and a real SIGINT in the middle of simulating (the run's dataset stage said
    `error: dataset stage stopped`, exit 2; dataset generate exited 130 without the line)."""
    (tmp_path / "spec.yaml").write_text(SLOW)
    proc = subprocess.Popen([sys.executable, "-m", "invphys.cli", *command, "--no-progress"], cwd=tmp_path,
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    store = tmp_path / ("run/dataset/store" if command[0] == "run" else "ds")
    deadline = time.monotonic() + 60
    while not list(store.glob("part-*.parquet")) and time.monotonic() < deadline:  # rows are being stored
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "interrupted" and "Traceback" not in err and "error:" not in err


def test_ctrl_c_anywhere_in_a_command_is_the_interrupted_line(monkeypatch) -> None:
    """Outside generation (training, inverting) typer turned KeyboardInterrupt into a silent exit 130."""
    import invphys.pipeline.runner as runner_module

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner_module, "run_spec", stop)
    result = runner.invoke(app, ["run", "spec.yaml", "--out", "run"])
    assert result.exit_code == 130 and result.stderr.strip() == "interrupted"


@pytest.mark.slow  # three real runs, one with MLflow (its SQLite schema): ~15 s
def test_quiet_and_silent_levels(tmp_path) -> None:
    """-q: no stage lines, progress bars or MLflow INFO lines; -qq: nothing at all on a success."""
    pytest.importorskip("mlflow")
    (tmp_path / "spec.yaml").write_text(TINY + "tracker: none\n")
    (tmp_path / "mlflow.yaml").write_text(TINY + "tracker: mlflow\n")

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "invphys.cli", *args], cwd=tmp_path, env=_env(),
                              capture_output=True, text=True, timeout=300)

    loud = cli("run", "spec.yaml", "--out", "a")
    assert loud.returncode == 0 and "done dataset" in loud.stderr and "finished" in loud.stdout
    quiet = cli("-q", "run", "mlflow.yaml", "--out", "b")  # no MLflow INFO lines (its database set-up)
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
    assert quiet.stdout.startswith("finished")
    silent = cli("-qq", "run", "spec.yaml", "--out", "c")
    assert silent.returncode == 0 and silent.stdout == "" and silent.stderr == ""
    bad = cli("-qq", "run", "missing.yaml", "--out", "d")
    assert bad.returncode == 2 and bad.stderr.startswith("error:")


def test_a_permission_or_read_only_error_is_the_users_one_line(monkeypatch) -> None:
    """The environment refusing a write (read-only disk, no permission) is not a bug: exit 2, one line."""
    import errno

    import invphys.pipeline.runner as runner_module

    def refuse(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system", "/mnt/ro/run")

    monkeypatch.setattr(runner_module, "run_spec", refuse)
    result = runner.invoke(app, ["run", "spec.yaml", "--out", "/mnt/ro/run"])
    assert result.exit_code == 2 and result.output.strip() == "error: /mnt/ro/run: Read-only file system"
    monkeypatch.setattr(runner_module, "run_spec", lambda *a, **k: (_ for _ in ()).throw(OSError("other")))
    assert runner.invoke(app, ["run", "spec.yaml", "--out", "x"]).exit_code == 1  # an OSError of ours: a bug
