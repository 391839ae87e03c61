"""CLI manners (issue 10): one line for unexpected errors, --version, -h, plain flags, unclipped pipes."""

from __future__ import annotations

import subprocess
import sys

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


def test_out_naming_a_file_is_a_user_error(tmp_path) -> None:
    taken = tmp_path / "taken"
    taken.write_text("precious")
    result = invphys_cli("simulate", "--simulator", "orange_peel", "--preset", "tiny", "--out", str(taken))
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == f"error: --out '{taken}' is a file; name a new or existing directory"
    assert taken.read_text() == "precious"
