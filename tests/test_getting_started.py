"""docs/getting-started.md works exactly as written: every shell command of its ```bash blocks is checked.

* ``pip install`` lines: each local project (``.``, ``examples/...``) exists and has the extras named; every
  dependency on one of this repository's distributions (they are not on PyPI: ``invphys-anisompm`` ...)
  is installed by the same or an earlier line; nothing pulls torch before the line that pins the CPU build;
* ``invphys`` commands: the cheap ones run here (exit 0); ``invphys run SPEC --out DIR`` validates SPEC;
* ``make`` targets exist in the Makefile; the venv lines are the usual two.

Any other command fails the test, so the page cannot drift from what is checked. ``.ci/run`` runs the
same commands in a fresh venv (``python tests/test_getting_started.py --script`` prints them).
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "getting-started.md"
CHEAP = {"plugins", "validate", "--help", "--version", "info"}  # invphys sub-commands run as written


def bash_blocks(text: str) -> list[list[str]]:
    """The ```bash fenced blocks of ``text``, each as its command lines (comments and blanks dropped)."""
    blocks = re.findall(r"^```bash\n(.*?)^```", text, flags=re.S | re.M)
    out = []
    for block in blocks:
        lines = [" ".join(shlex.split(line, comments=True)) for line in block.splitlines()]
        out.append([line for line in lines if line])
    return out


def commands(text: str) -> list[list[str]]:
    """Every simple command of the page's bash blocks, in order (``a && b`` gives two)."""
    out = []
    for block in bash_blocks(text):
        for line in block:
            for part in re.split(r"\s*&&\s*", line):
                out.append(shlex.split(part))
    return out


# -- pip ------------------------------------------------------------------------------------------------
def _projects() -> dict[str, Path]:
    """This repository's distributions: canonical name -> project folder."""
    found = {}
    for p in [ROOT / "pyproject.toml", *sorted((ROOT / "examples").glob("*/pyproject.toml"))]:
        found[canonicalize_name(tomllib.loads(p.read_text())["project"]["name"])] = p.parent
    return found


def _meta(folder: Path) -> dict:
    return tomllib.loads((folder / "pyproject.toml").read_text())["project"]


@dataclass
class PipLine:
    """One ``pip install``: the local projects (folder, extras) and the named requirements."""

    local: list[tuple[Path, set[str]]] = field(default_factory=list)
    named: list[Requirement] = field(default_factory=list)


def parse_pip(argv: list[str]) -> PipLine:
    """Parse ``pip install [-q] [-U] [-e] REQ ...``; options taking a value are refused (not used here)."""
    assert argv[:2] == ["pip", "install"] or argv[:4] == ["python", "-m", "pip", "install"], argv
    line = PipLine()
    for arg in argv[argv.index("install") + 1:]:
        if arg in ("-e", "--editable", "-q", "--quiet", "-U", "--upgrade"):
            continue
        assert not arg.startswith("-"), f"pip option {arg!r} is not understood by this test"
        m = re.fullmatch(r"((?:\.|\.\.|examples)(?:/[\w.-]+)*)(?:\[([\w,\s-]*)\])?", arg)
        if m:
            extras = {e.strip() for e in (m.group(2) or "").split(",") if e.strip()}
            line.local.append(((ROOT / m.group(1)).resolve(), extras))
        else:
            line.named.append(Requirement(arg))
    return line


def closure(folder: Path, extras: set[str], projects: dict[str, Path]) -> tuple[list[Requirement], list[str]]:
    """Every requirement ``folder[extras]`` pulls (local distributions followed), and the problems found."""
    reqs: list[Requirement] = []
    problems: list[str] = []
    seen: set[tuple[str, frozenset[str]]] = set()
    todo = [(folder, set(extras))]
    while todo:
        here, want = todo.pop()
        meta = _meta(here)
        key = (meta["name"], frozenset(want))
        if key in seen:
            continue
        seen.add(key)
        optional = meta.get("optional-dependencies", {})
        for e in sorted(want - set(optional)):
            problems.append(f"{meta['name']} has no extra [{e}] (extras: {', '.join(sorted(optional))})")
        deps = list(meta.get("dependencies", [])) + [d for e in sorted(want & set(optional)) for d in optional[e]]
        for d in map(Requirement, deps):
            reqs.append(d)
            local = projects.get(canonicalize_name(d.name))
            if local is not None:
                todo.append((local, set(d.extras)))
    return reqs, problems


def check_pip_lines(lines: list[PipLine]) -> list[str]:
    """Problems of a page's pip lines, installed in order into one venv."""
    projects = _projects()
    installed: set[str] = set()
    torch_pinned = False
    problems: list[str] = []
    for n, line in enumerate(lines, 1):
        for folder, _ in line.local:
            if not (folder / "pyproject.toml").is_file():
                problems.append(f"pip line {n}: {folder} is not a project of this repository")
        if any(not (f / "pyproject.toml").is_file() for f, _ in line.local):
            continue
        here = {canonicalize_name(_meta(f)["name"]) for f, _ in line.local}
        pulled: list[Requirement] = list(line.named)
        for folder, extras in line.local:
            reqs, bad = closure(folder, extras, projects)
            problems += [f"pip line {n}: {b}" for b in bad]
            pulled += reqs
        for r in pulled:
            name = canonicalize_name(r.name)
            if name in projects and name not in installed | here:
                problems.append(f"pip line {n}: {r} is a distribution of this repository (not on PyPI) that "
                                f"neither this line nor an earlier one installs (add -e {projects[name].relative_to(ROOT)})")
            if name == "torch" and not torch_pinned and r not in line.named:
                problems.append(f"pip line {n} pulls torch before a line pins torch==... (the CPU build)")
        torch_pinned |= any(canonicalize_name(r.name) == "torch" and "==" in str(r.specifier) for r in line.named)
        installed |= here
    return problems


# -- the page -------------------------------------------------------------------------------------------
def _kind(argv: list[str]) -> str:
    if argv[:3] == ["python3", "-m", "venv"] or argv[:1] in (["."], ["source"]):
        return "venv"
    if argv[:2] == ["pip", "install"] or argv[:4] == ["python", "-m", "pip", "install"]:
        return "pip"
    return {"invphys": "invphys", "make": "make"}.get(argv[0], "unknown")


def _page() -> list[list[str]]:
    return commands(DOC.read_text())


def test_the_page_has_only_commands_this_test_checks() -> None:
    cmds = _page()
    unknown = [" ".join(c) for c in cmds if _kind(c) == "unknown"]
    assert not unknown, f"commands this test does not check: {unknown}"
    kinds = {_kind(c) for c in cmds}
    assert {"pip", "invphys", "make", "venv"} <= kinds, kinds


def test_the_pip_lines_install_every_distribution_they_need() -> None:
    lines = [parse_pip(c) for c in _page() if _kind(c) == "pip"]
    assert lines and any(line.local for line in lines)
    assert check_pip_lines(lines) == []


def test_the_readme_install_lines_resolve_too() -> None:
    lines = [parse_pip(c) for c in commands((ROOT / "README.md").read_text()) if c and _kind(c) == "pip"]
    assert lines and check_pip_lines(lines) == []


def test_the_pip_check_finds_a_missing_engine_and_unknown_extras() -> None:
    """The check itself: the line the page had before (no examples/anisompm) and a misspelt extra fail."""
    old = [parse_pip(shlex.split("pip install torch==2.13.0")),
           parse_pip(shlex.split('pip install -e ".[all]" -e examples/orange_peel'))]
    problems = check_pip_lines(old)
    assert any("invphys-anisompm" in p for p in problems), problems
    assert any("[tiachi]" in p for p in check_pip_lines([parse_pip(["pip", "install", "torch==2.13.0"]),
                                                          parse_pip(["pip", "install", ".[tiachi]"])]))
    assert any("pulls torch" in p for p in check_pip_lines([parse_pip(["pip", "install", ".[torch]"])]))


def test_the_make_targets_exist() -> None:
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), flags=re.M))
    named = {t for c in _page() if _kind(c) == "make" for t in c[1:]}
    assert named and named <= targets, named - targets


def _invphys() -> list[str]:
    exe = Path(sys.executable).parent / "invphys"
    return [str(exe)] if exe.is_file() else [sys.executable, "-c", "from invphys.cli import main; main()"]


@pytest.mark.parametrize("argv", [c for c in _page() if _kind(c) == "invphys"], ids=" ".join)
def test_the_invphys_commands_run(argv: list[str]) -> None:
    """Cheap commands run as written; ``invphys run SPEC --out DIR`` validates SPEC (running it is make demo)."""
    if argv[1] == "run":
        spec = argv[2]
        assert "--out" in argv and argv[argv.index("--out") + 1].startswith("runs/"), argv
        argv = ["invphys", "validate", spec]
    assert argv[1] in CHEAP, f"{' '.join(argv)}: not a cheap command; extend the test"
    res = subprocess.run(_invphys() + argv[1:], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr


def script() -> str:
    """The page's commands (venv, pip, invphys) as one bash script, for a fresh venv in CI."""
    lines = [" ".join(shlex.quote(a) for a in c) for c in _page() if _kind(c) in ("venv", "pip", "invphys")]
    return "set -euxo pipefail\n" + "\n".join(lines) + "\n"


if __name__ == "__main__":
    if sys.argv[1:] != ["--script"]:
        sys.exit("usage: python tests/test_getting_started.py --script")
    print(script(), end="")
