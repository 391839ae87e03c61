"""Comparing an older engine with this tree's means listing the older copy first on PYTHONPATH: a benchmark
must not put this tree's packages in front of it, or an old/new pair compares the new code with itself (the engine's
own benchmarks are checked in ``examples/anisompm/tests/test_engine_benchmark_paths.py``); and what a written result
records of the script that made it."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p.name for p in (ROOT / "benchmarks").glob("bench_*.py"))


def test_no_benchmark_prepends_the_tree_unconditionally():
    offenders = [s for s in SCRIPTS if "sys.path[:0]" in (ROOT / "benchmarks" / s).read_text()]
    assert offenders == []


def test_a_written_result_names_its_script_and_command(tmp_path, monkeypatch, capsys):
    """``_machine.emit`` starts every result with the script and command that made it (benchmarks/README.md)."""
    import json

    from benchmark_modules import load

    machine = load("_machine")
    monkeypatch.setattr(sys, "argv", [str(ROOT / "benchmarks" / "bench_dataset.py"), "--n", "2", "--tag", "a b"])
    machine.emit({"wall_s": 1.0}, tmp_path / "r" / "out.json")
    rec = json.loads((tmp_path / "r" / "out.json").read_text())
    assert rec["script"] == "benchmarks/bench_dataset.py"
    assert rec["command"] == "python benchmarks/bench_dataset.py --n 2 --tag 'a b'"
    assert rec["wall_s"] == 1.0
    machine.emit({"command": "as recorded"}, tmp_path / "own.json")
    assert json.loads((tmp_path / "own.json").read_text())["command"] == "as recorded"
