"""Layers look down only: an AST check of every import in ``invphys/`` (top-level and lazy ones alike).

::

    cli/                       commands
    pipeline/                  runner, stages, stage context
    models/ plugins/ envs/     networks and training loops, built-in plugins, Gymnasium environments,
    inverter/ evaluation/      trained bundles, recovery statistics (these may use one another, never pipeline or cli)
    tracking/                  where training curves and final metrics go
    core/                      interfaces, parameter spaces, objectives, specs, the dataset store

Nothing in ``invphys/`` imports an example distribution (``examples/*``, e.g. ``invphys_orange_peel``).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "invphys"
EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

#: package -> the invphys packages it must never import
FORBIDDEN: dict[str, tuple[str, ...]] = {
    "core": ("models", "plugins", "envs", "tracking", "inverter", "pipeline", "cli"),
    "tracking": ("models", "plugins", "envs", "inverter", "pipeline", "cli"),
    "inverter": ("pipeline", "cli"),
    "evaluation": ("pipeline", "cli"),
    "models": ("pipeline", "cli"),
    "plugins": ("pipeline", "cli"),
    "envs": ("pipeline", "cli"),
    "pipeline": ("cli",),
}


def _example_packages() -> set[str]:
    """Top-level import names of the example distributions (folders holding an ``__init__.py``)."""
    names = {"examples"}
    for init in EXAMPLES.glob("*/*/__init__.py"):
        names.add(init.parent.name)
    return names


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import statement in a module, relative ones resolved."""
    module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            found.append((node.lineno, name))
            # ``from invphys import models`` imports the subpackage
            found += [(node.lineno, f"{name}.{a.name}") for a in node.names if name == "invphys"]
    return found


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "invphys" else None


def violations() -> list[str]:
    examples = _example_packages()
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        here = _layer(".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts))
        for line, name in imported_modules(path):
            where = f"{path.relative_to(PACKAGE.parent)}:{line}"
            if name.split(".")[0] in examples:
                problems.append(f"{where} imports the example package {name}")
            target = _layer(name)
            if here in FORBIDDEN and target in FORBIDDEN[here]:
                problems.append(f"{where}: invphys.{here} imports {name} (a higher layer)")
    return problems


def test_layers_only_look_down() -> None:
    assert violations() == []


def test_core_imports_nothing_above_it() -> None:
    core = list((PACKAGE / "core").rglob("*.py"))
    assert len(core) > 5
    above = {"models", "plugins", "envs", "tracking", "inverter", "pipeline", "cli"}
    for path in core:
        assert not [n for _, n in imported_modules(path) if _layer(n) in above], path


@pytest.mark.parametrize(("source", "expected"), [
    ("from invphys.pipeline.runner import run_spec\n", "invphys.core.x imports invphys.pipeline.runner"),
    ("def f():\n    import invphys.models.nets\n", "invphys.core.x imports invphys.models.nets"),
    ("from .. import cli\n", "invphys.core.x imports invphys.cli"),
    ("from invphys import plugins\n", "invphys.core.x imports invphys.plugins"),
    ("import invphys_orange_peel\n", "example package invphys_orange_peel"),
])
def test_the_check_catches_an_upward_import(tmp_path, monkeypatch, source, expected) -> None:
    """The checker itself: a planted upward import (top-level, lazy or relative) is reported."""
    pkg = tmp_path / "invphys"
    (pkg / "core").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "core" / "__init__.py").write_text("")
    (pkg / "core" / "x.py").write_text(source)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    found = violations()
    assert len(found) == 1 and expected.split(" imports ")[-1] in found[0], found
