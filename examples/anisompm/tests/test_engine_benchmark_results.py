"""``examples/anisompm/benchmarks/results/`` holds one current result per engine benchmark, as the framework's
``benchmarks/results/`` does: each JSON names the script that made it (at its path in the repository), the command
and the device; no two name the same script; the README's table lists each."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
HERE = ROOT / "examples" / "anisompm" / "benchmarks"


def results() -> list[Path]:
    """The tracked files of the engine's ``benchmarks/results/`` (a result just written is not yet the current one)."""
    out = subprocess.run(["git", "ls-files", "--", str(HERE / "results")], cwd=ROOT, capture_output=True, text=True)
    return [ROOT / p for p in out.stdout.split()] if out.returncode == 0 else sorted((HERE / "results").glob("*"))


def test_there_are_results_and_each_names_its_script_command_and_device() -> None:
    assert len(results()) >= 6
    bad = []
    for p in results():
        if p.suffix != ".json":
            bad.append(f"{p.name}: not a JSON result")
            continue
        rec = json.loads(p.read_text())
        for key in ("script", "command", "device"):
            if not isinstance(rec.get(key), str) or not rec[key].strip():
                bad.append(f"{p.name}: no {key!r}")
        script = rec.get("script", "")
        if not (ROOT / script).is_file() or not script.startswith("examples/anisompm/benchmarks/"):
            bad.append(f"{p.name}: script {script!r} is not one of the engine's benchmarks")
        elif script not in rec.get("command", ""):
            bad.append(f"{p.name}: the command does not run {script}")
    assert bad == []


def test_one_result_per_benchmark_and_the_readme_lists_each() -> None:
    by_script: dict[str, list[str]] = {}
    for p in results():
        by_script.setdefault(json.loads(p.read_text()).get("script"), []).append(p.name)
    assert {s: n for s, n in by_script.items() if len(n) > 1} == {}
    readme = (HERE / "README.md").read_text()
    assert [p.name for p in results() if p.name not in readme] == []
