"""The engine's benchmarks (``examples/anisompm/benchmarks/``): comparing an older engine with this tree's means
listing the older copy first on PYTHONPATH, so a benchmark must not put this tree's packages in front of it (or an
old/new pair compares the new code with itself); and a written result names the script at its path here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
BENCHMARKS = ROOT / "examples" / "anisompm" / "benchmarks"
SCRIPTS = sorted(p.name for p in BENCHMARKS.glob("*.py"))


def test_no_engine_benchmark_prepends_the_tree_unconditionally():
    assert "bench_resort.py" in SCRIPTS and "bench_tiled_p2g.py" in SCRIPTS
    offenders = [s for s in SCRIPTS if "sys.path[:0]" in (BENCHMARKS / s).read_text()]
    assert offenders == []


@pytest.mark.parametrize("script", ["bench_continuous_gpu.py", "bench_resort.py", "bench_tiled_p2g.py"])
def test_an_engine_listed_first_on_pythonpath_is_the_one_imported(tmp_path, script):
    old = tmp_path / "old"
    (old / "invphys_anisompm").mkdir(parents=True)
    (old / "invphys_anisompm" / "__init__.py").write_text("MARK = 'older copy'\n")
    # as `python examples/anisompm/benchmarks/<script>` would: the script's folder is on the path too
    path = [old, ROOT, ROOT / "examples" / "anisompm", ROOT / "examples" / "orange_peel", ROOT / "benchmarks",
            BENCHMARKS]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(map(str, path))}
    code = (f"import runpy; runpy.run_path({str(BENCHMARKS / script)!r}, run_name='probe'); "
            "import invphys_anisompm; print(getattr(invphys_anisompm, 'MARK', invphys_anisompm.__file__))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "older copy"


def test_a_result_written_from_here_names_this_script(tmp_path):
    """Run from anywhere, a benchmark that writes with the framework's ``_machine.emit`` records its path in the
    repository, the one its README table and command give."""
    pytest.importorskip("taichi")
    out = tmp_path / "grid.json"
    proc = subprocess.run([sys.executable, str(BENCHMARKS / "check_grid_box.py"), "--preset", "tiny", "--arch", "cpu",
                           "--batch", "1", "--frames", "1", "--steps", "1", "--out", str(out)],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.exists(), proc.stderr[-2000:]
    rec = json.loads(out.read_text())
    assert rec["script"] == "examples/anisompm/benchmarks/check_grid_box.py"
    assert rec["command"].startswith("python ")
