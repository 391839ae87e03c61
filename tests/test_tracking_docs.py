"""The runnable examples of docs/tracking.md run, and its YAML settings are valid tracker sections."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

DOC = Path(__file__).resolve().parent.parent / "docs" / "tracking.md"


def blocks(language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```$", DOC.read_text(), re.S | re.M)


def test_the_python_example_runs_and_prints_one_point_per_epoch(tmp_path, monkeypatch, capsys) -> None:
    (code,) = blocks("python")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, str(DOC), "exec"), {"__name__": "__doc_example__"})
    assert capsys.readouterr().out.strip().endswith("30")
    assert list((tmp_path / "runs" / "notebook" / "tensorboard").glob("events.out.tfevents.*"))


def test_every_yaml_setting_is_a_valid_tracker_section() -> None:
    from invphys.core.spec import TrackerSection

    settings = [yaml.safe_load(b)["tracker"] for b in blocks("yaml")]
    assert [TrackerSection.model_validate(s).type for s in settings] == ["tensorboard", "none", "mlflow"]
