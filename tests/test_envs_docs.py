"""The runnable example of docs/gymnasium.md runs: a surrogate, gym.make, check_env and SB3's PPO."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parent.parent / "docs" / "gymnasium.md"


def test_the_gymnasium_example_runs(tmp_path, monkeypatch, capsys) -> None:
    pytest.importorskip("stable_baselines3")
    (code,) = re.findall(r"^```python\n(.*?)^```$", DOC.read_text(), re.S | re.M)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, str(DOC), "exec"), {"__name__": "__doc_example__"})
    out = capsys.readouterr().out.strip()
    reward = float(out.rsplit(" ", 1)[-1])
    assert 0.0 < reward <= 1.0
    assert "'theta_0': " in out.splitlines()[-2]  # info names the state's parameters
