"""Standard logging on the command line: stage messages at the default level, fewer with -q, more with -v."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

SPEC = """
name: logging-levels
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 24, batch_size: 24}
surrogate: {type: mlp, hidden: [8, 8, 8], max_epochs: 3}
stages: [dataset, train]
"""


@pytest.fixture(autouse=True)
def _restore_invphys_logger():
    """The CLI configures the ``invphys`` logger; leave it as found for the tests that follow."""
    logger = logging.getLogger("invphys")
    saved = (list(logger.handlers), logger.level, logger.propagate)
    yield
    logger.handlers[:], logger.level, logger.propagate = saved[0], saved[1], saved[2]


def _run(tmp_path: Path, *flags: str) -> str:
    """``invphys [flags] run spec.yaml`` in-process (typer's runner); returns what went to stderr."""
    from typer.testing import CliRunner

    from invphys.cli import app

    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC)
    result = CliRunner().invoke(app, [*flags, "run", str(spec), "--out", str(tmp_path / "run"), "--no-progress"])
    assert result.exit_code == 0, result.output
    return result.stderr


@pytest.mark.parametrize(("flags", "shown", "hidden"), [
    ((), ["train: training surrogate 'mlp'", "held-out R^2"], ["TensorBoard events in"]),
    (("-q",), [], ["training surrogate", "held-out R^2"]),
    (("-v",), ["training surrogate", "TensorBoard events in"], []),
])
def test_cli_log_levels(tmp_path, flags, shown, hidden) -> None:
    err = _run(tmp_path, *flags)
    for text in shown:
        assert text in err, err
    for text in hidden:
        assert text not in err, err
