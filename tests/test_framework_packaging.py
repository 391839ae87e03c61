"""Example distributions ship their specs: a built wheel holds every YAML file of the package folder."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = sorted(p.parent for p in (ROOT / "examples").glob("*/pyproject.toml"))

pytest.importorskip("setuptools")


def _source_yaml(project: Path) -> set[str]:
    """``package/.../x.yaml`` paths of the YAML files inside the project's package folders."""
    found = set()
    for pkg in project.iterdir():
        if pkg.is_dir() and (pkg / "__init__.py").is_file():
            found |= {p.relative_to(project).as_posix() for p in pkg.rglob("*.yaml")}
    return found


def test_the_orange_peel_specs_live_inside_its_package() -> None:
    project = ROOT / "examples" / "orange_peel"
    assert {"invphys_orange_peel/specs/quickstart.yaml", "invphys_orange_peel/specs/paper.yaml"} <= _source_yaml(project)
    assert not (project / "specs").exists(), "specs outside the package are not shipped by the wheel"


@pytest.mark.parametrize("project", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_the_wheel_ships_every_spec(project: Path, tmp_path: Path) -> None:
    src = tmp_path / project.name  # build from a copy: no build/ or egg-info left in the checkout
    shutil.copytree(project, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                          "--no-index", "-w", str(tmp_path / "dist"), str(src)], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    (wheel,) = (tmp_path / "dist").glob("*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = _source_yaml(project) - names
    assert not missing, f"{wheel.name} lacks {sorted(missing)}: list them in [tool.setuptools.package-data]"


USER_EXTRAS = {"torch", "taichi", "warp", "optim", "optuna", "sbi", "rl", "ray", "mlflow"}
TEAM_TOOLS = {"pytest", "pytest-xdist", "hypothesis", "ruff", "mypy", "mkdocs-material", "mkdocstrings", "types-pyyaml",
              "jsonschema"}


def test_each_need_has_its_extra_and_all_is_the_user_set_without_the_team_tools() -> None:
    from packaging.utils import canonicalize_name
    from test_getting_started import _projects, closure

    optional = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert USER_EXTRAS | {"dev", "all"} <= set(optional)
    assert any(r.startswith("optuna>=3.6") for r in optional["optuna"])
    user, problems = closure(ROOT, {"all"}, _projects())
    assert problems == []
    names = {canonicalize_name(r.name) for r in user}
    assert not names & TEAM_TOOLS, f"invphys[all] pulls the team's tools {sorted(names & TEAM_TOOLS)}"
    for extra in USER_EXTRAS:  # all = every user extra
        assert {canonicalize_name(r.name) for r in closure(ROOT, {extra}, _projects())[0]} <= names, extra
    dev = {canonicalize_name(r.name) for r in closure(ROOT, {"dev"}, _projects())[0]}
    assert {"pytest", "ruff", "mypy", "mkdocs-material"} <= dev


def test_the_examples_extras_name_existing_engine_extras() -> None:
    from test_getting_started import _projects, closure

    for project in EXAMPLES:
        extras = set(tomllib.loads((project / "pyproject.toml").read_text())["project"].get("optional-dependencies", {}))
        assert closure(project, extras, _projects())[1] == [], project.name
