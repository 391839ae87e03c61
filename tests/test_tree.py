"""What the tracked tree holds: the product, not its measurement history or the team's machinery.

- Apart from shipped bundles (``inverters/``) and committed datasets (``datasets/``), the tracked files weigh
  at most 8 MiB (their sizes in bytes; measurement history lives in git history, not in the tree).
- No tracked file speaks of how the developers reached their GPUs (the words in :data:`WORKPLACE`).
- ``benchmarks/results/`` holds one current result per benchmark: each JSON names the benchmark script (or
  spec) that made it, the command and the device, and no two name the same one (``benchmarks/README.md``).
- Rooms a newcomer can hold in their head: no module in ``invphys/`` over :data:`MAX_FILE_LINES` lines and no
  function (or method) over :data:`MAX_FUNCTION_LINES`, from its ``def`` line to its last line. A module that
  must be bigger says so and why in its docstring, on a line starting with :data:`SIZE_EXCEPTION`; every
  exception (and every debt in :data:`SIZE_DEBTS`) is shown in the test output as a warning.
"""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
import warnings
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


MAX_FILE_LINES = 600
MAX_FUNCTION_LINES = 80
#: the docstring line by which a module states that it may be bigger, and why
SIZE_EXCEPTION = "Size exception:"
#: oversize functions today in modules whose owners are still at work, each a debt (remove the line when paid)
SIZE_DEBTS: dict[str, str] = {}


class SizeNote(UserWarning):
    """A module excepted from the size rule, or a size debt: shown, not failed."""


def _functions(tree: ast.AST, prefix: str = "") -> list[tuple[str, int]]:
    """(qualified name, lines from ``def`` to the last line) of every function and method, nested ones too."""
    found = []
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            name = f"{prefix}{node.name}"
            if not isinstance(node, ast.ClassDef):
                found.append((name, (node.end_lineno or node.lineno) - node.lineno + 1))
            found += _functions(node, name + ".")
        else:
            found += _functions(node, prefix)
    return found


def room_sizes(folder: Path | None = None) -> dict[str, tuple[list[str], str | None]]:
    """``{module: (what is over the limits, the stated exception or None)}`` for the modules of ``folder``
    (default ``invphys/``) over a limit or stating an exception; each item is ``"path (N lines)"`` or
    ``"path:function (N lines)"``."""
    folder = ROOT / "invphys" if folder is None else folder
    out = {}
    for path in sorted(folder.rglob("*.py")):
        text = path.read_text()
        tree = ast.parse(text, filename=str(path))
        rel = path.relative_to(folder.parent).as_posix()
        n = len(text.splitlines())
        over = [f"{rel} ({n} lines)"] if n > MAX_FILE_LINES else []
        over += [f"{rel}:{name} ({k} lines)" for name, k in _functions(tree) if k > MAX_FUNCTION_LINES]
        stated = [line.strip()[len(SIZE_EXCEPTION):].strip() for line in (ast.get_docstring(tree) or "").splitlines()
                  if line.strip().startswith(SIZE_EXCEPTION)]
        if over or stated:
            out[rel] = (over, stated[0] if stated else None)
    return out


def _key(item: str) -> str:
    return item.rsplit(" (", 1)[0]


def size_report(folder: Path | None = None) -> tuple[list[str], list[str], list[str]]:
    """(items breaking the rule, notes on stated exceptions and debts, bad exceptions) for ``folder``."""
    broken, notes, bad = [], [], []
    for rel, (over, why) in room_sizes(folder).items():
        if why is not None:
            notes.append(f"size exception: {rel} ({'; '.join(i.split(' (', 1)[1][:-1] for i in over)}): {why}")
            if not why or not over:
                bad.append(f"{rel}: {'no reason given' if not why else 'within the limits, drop the exception'}")
            continue
        for item in over:
            if _key(item) in SIZE_DEBTS:
                notes.append(f"size debt: {item}: {SIZE_DEBTS[_key(item)]}")
            else:
                broken.append(item)
    return broken, notes, bad


def test_no_module_over_600_lines_and_no_function_over_80_in_invphys() -> None:
    broken, notes, _ = size_report()
    for note in notes:
        warnings.warn(SizeNote(note), stacklevel=1)
    assert broken == [], (f"over {MAX_FILE_LINES} lines a module or {MAX_FUNCTION_LINES} a function: split it, or "
                          f"state '{SIZE_EXCEPTION} <why>' in the module docstring:\n" + "\n".join(broken))


def test_a_size_exception_says_why_and_is_needed() -> None:
    assert size_report()[2] == []


def test_size_debts_are_still_owed() -> None:
    """A paid debt leaves :data:`SIZE_DEBTS`, so the list only shrinks."""
    owed = {_key(item) for over, why in room_sizes().values() if why is None for item in over}
    assert sorted(set(SIZE_DEBTS) - owed) == []


def test_the_size_rule_sees_big_modules_long_functions_and_stated_exceptions(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    (pkg / "long.py").write_text("class A:\n    def run(self):\n" + body.replace("    ", "        ") + "\n")
    (pkg / "fits.py").write_text(f"def run():\n{body[: body.rindex(chr(10))]}\n")
    (pkg / "big.py").write_text("\n" * MAX_FILE_LINES + "x = 1\n")
    (pkg / "said.py").write_text('"""A table.\n\nSize exception: one generated table.\n"""\n' + "\n" * MAX_FILE_LINES)
    (pkg / "unneeded.py").write_text('"""Small.\n\nSize exception: none really.\n"""\n')
    (pkg / "silent.py").write_text('"""Big.\n\nSize exception:\n"""\n' + "\n" * MAX_FILE_LINES)
    broken, notes, bad = size_report(pkg)
    assert broken == [f"pkg/big.py ({MAX_FILE_LINES + 1} lines)", f"pkg/long.py:A.run ({MAX_FUNCTION_LINES + 1} lines)"]
    assert f"size exception: pkg/said.py ({MAX_FILE_LINES + 4} lines): one generated table." in notes
    assert bad == ["pkg/silent.py: no reason given", "pkg/unneeded.py: within the limits, drop the exception"]
