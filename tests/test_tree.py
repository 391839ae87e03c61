"""What the tracked tree holds: the product, not its measurement history or the team's machinery.

- Apart from shipped bundles (``inverters/``) and committed datasets (``datasets/``), the tracked files weigh
  at most 8 MiB (their sizes in bytes; measurement history lives in git history, not in the tree).
- No tracked file speaks of how the developers reached their GPUs (the words in :data:`WORKPLACE`).
- ``benchmarks/results/`` holds one current result per benchmark: each JSON names the benchmark script (or
  spec) that made it, the command and the device, and no two name the same one (``benchmarks/README.md``).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIMIT_BYTES = 8 * 1024 * 1024
#: trees whose size grows with the data chosen to ship, outside the limit
SHIPPED = ("inverters/", "datasets/")

#: phrases of the team's own GPU plumbing, never part of the product (written in pieces so that this file,
#: which must name them, does not match itself)
WORKPLACE = tuple("".join(p) for p in [
    ("device", " tool"), ("device", "-tool"), ("device", " call"), (".g", "pu/"), ("pack_for", "_gpu"),
    ("nvidia-h100", "-x"), ("nvidia-h200", "-x"), ("ensure", "_staged"), ("split_taichi", "_wheels"),
    ("split", "_ray.sh"), ("/root", "/out"), ("datasets/", "device/"), ("benchmarks/", "device/"),
    ("carry", " limit"), ("call's", " carry"), ("64", " MiB carr"), ("taichi", " staged"),
])

#: files of other owners that still hold such phrases, to be cleaned (remove a line when its file is clean)
PENDING: set[str] = set()
#: a bare ignore pattern for a local scratch folder is not prose about it
EXEMPT = {".gitignore", "tests/test_tree.py"}


def tracked() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
    return [p for p in out.stdout.decode().split("\0") if p and (ROOT / p).is_file()]


def text_of(path: str) -> str | None:
    data = (ROOT / path).read_bytes()
    if b"\0" in data[:8192]:
        return None
    return data.decode("utf-8", errors="replace")


def test_the_tree_apart_from_bundles_and_datasets_is_at_most_8_mib() -> None:
    sizes = {p: (ROOT / p).stat().st_size for p in tracked() if not p.startswith(SHIPPED)}
    total = sum(sizes.values())
    largest = sorted(sizes.items(), key=lambda kv: -kv[1])[:10]
    assert total <= LIMIT_BYTES, f"{total / 2**20:.2f} MiB tracked outside {SHIPPED}; largest: {largest}"


def test_no_tracked_file_speaks_of_the_gpu_plumbing() -> None:
    hits = []
    for path in tracked():
        if path in EXEMPT or path in PENDING:
            continue
        text = text_of(path)
        if text is None:
            continue
        low = text.lower()
        hits += [f"{path}: {w!r}" for w in WORKPLACE if w.lower() in low]
    assert hits == []


def results() -> list[Path]:
    """The tracked files of ``benchmarks/results/`` (a result just written there is not yet the current one)."""
    return [ROOT / p for p in tracked() if p.startswith("benchmarks/results/")]


def test_benchmark_results_are_json_naming_script_command_and_device() -> None:
    bad = []
    for p in results():
        if p.suffix != ".json":
            bad.append(f"{p.name}: not a JSON result")
            continue
        rec = json.loads(p.read_text())
        for key in ("script", "command", "device"):
            if not isinstance(rec.get(key), str) or not rec[key].strip():
                bad.append(f"{p.name}: no {key!r}")
        if isinstance(rec.get("script"), str) and not (ROOT / rec["script"]).is_file():
            bad.append(f"{p.name}: script {rec['script']} does not exist")
    assert bad == []


def test_at_most_one_result_per_benchmark() -> None:
    by_script: dict[str, list[str]] = {}
    for p in results():
        if p.suffix == ".json":
            by_script.setdefault(json.loads(p.read_text()).get("script"), []).append(p.name)
    assert {s: n for s, n in by_script.items() if len(n) > 1} == {}


def test_the_benchmarks_readme_lists_every_result() -> None:
    readme = (ROOT / "benchmarks" / "README.md").read_text()
    missing = [p.name for p in results() if p.name not in readme]
    assert missing == []
