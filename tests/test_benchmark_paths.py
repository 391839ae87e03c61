"""Comparing an older engine with this tree's means listing the older copy first on PYTHONPATH: a benchmark
must not put this tree's packages in front of it, or an old/new pair compares the new code with itself."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p.name for p in (ROOT / "benchmarks").glob("bench_*.py"))


def test_no_benchmark_prepends_the_tree_unconditionally():
    offenders = [s for s in SCRIPTS if "sys.path[:0]" in (ROOT / "benchmarks" / s).read_text()]
    assert offenders == []


@pytest.mark.parametrize("script", ["bench_continuous_gpu.py", "bench_resort.py", "bench_tiled_p2g.py"])
def test_an_engine_listed_first_on_pythonpath_is_the_one_imported(tmp_path, script):
    old = tmp_path / "old"
    (old / "invphys_anisompm").mkdir(parents=True)
    (old / "invphys_anisompm" / "__init__.py").write_text("MARK = 'older copy'\n")
    # as `python benchmarks/<script>` would: the script's folder is on the path too
    path = [old, ROOT, ROOT / "examples" / "anisompm", ROOT / "examples" / "orange_peel", ROOT / "benchmarks"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(map(str, path))}
    code = (f"import runpy; runpy.run_path({str(ROOT / 'benchmarks' / script)!r}, run_name='probe'); "
            "import invphys_anisompm; print(getattr(invphys_anisompm, 'MARK', invphys_anisompm.__file__))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "older copy"


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
