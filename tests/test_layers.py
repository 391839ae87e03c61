"""Layers look down only, and modules import no circles: an AST check of every import in ``invphys/`` and the
example packages (top-level, lazy and relative imports, and ``importlib.import_module`` with a literal name).

The layers, lowest first (a module may import its own layer and those below it)::

    invphys (__init__)         the public names (lazily re-exported)
    cli                        commands
    pipeline                   runner, stages, stage context
    inversion_env              the Gymnasium env invphys/Inversion-v0 (from a surrogate or a bundle)
    evaluation  inverter       recovery statistics, trained bundles (these may use one another)
    plugins  evaluators  envs  built-in plugins (surrogates, latents, optimisers, baselines, executors, ...),
                               what searches score (uncertainty penalty, the simulator in the loop, polish, refine),
                               Gymnasium environments (the PPO optimisers train on them)
    data                       dataset generation and adaptive design (they build plugins)
    models                     networks and training loops
    tracking                   where training curves and final metrics go
    registry  testing          finding plugins; conformance checks for plugin authors
    core                       interfaces, parameter spaces, objectives, specs, the dataset store

The example distributions sit above all of ``invphys``: the AnisoMPM engine (``invphys_anisompm``) below the
foods built on it (orange peel, cheese cut), and the toy spring beside them; no food imports another, and
nothing in ``invphys/`` imports an example.

Imports that break these rules today are listed in :data:`KNOWN_UPWARD` and :data:`KNOWN_CIRCLES`, each a
debt to pay (the renovation's "floors only look down"): a new one fails the test, and an entry that the code
no longer needs fails it too, so the lists only shrink.
"""

from __future__ import annotations

import ast
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "invphys"
EXAMPLES = ROOT / "examples"

#: lowest first; a module belongs to the layer of its longest matching prefix
LAYERS: tuple[tuple[str, ...], ...] = (
    ("invphys.core",),
    ("invphys.registry", "invphys.testing"),
    ("invphys.tracking",),
    ("invphys.models",),
    ("invphys.plugins", "invphys.evaluators", "invphys.envs"),
    ("invphys.data",),
    ("invphys.evaluation", "invphys.inverter"),
    ("invphys.inversion_env",),
    ("invphys.pipeline",),
    ("invphys.cli",),
    ("invphys",),
    ("invphys_anisompm",),
    ("invphys_orange_peel", "invphys_cheese_cut", "invphys_toy_spring"),
)
#: packages of one layer that must not import each other (independent examples)
SIBLINGS_APART = ({"invphys_orange_peel", "invphys_cheese_cut", "invphys_toy_spring"},)

#: (importer, imported) pairs that look up today, with why; remove an entry when its import goes
KNOWN_UPWARD: dict[tuple[str, str], str] = {
}

#: import circles today (strongly connected modules); each found circle must lie inside one of these
KNOWN_CIRCLES: tuple[frozenset[str], ...] = ()

#: ``importlib.import_module`` calls whose module is not a literal: the file, and why it is safe
DYNAMIC_IMPORT_SITES: dict[str, str] = {
    "examples/anisompm/invphys_anisompm/backends/__init__.py": "a backend of the fixed BACKENDS table",
    "invphys/registry.py": "a 'package.module:Class' plugin path the user names",
}


def package_roots() -> list[tuple[Path, Path]]:
    """(package folder, the folder its import names are relative to) for invphys and every example."""
    roots = [(PACKAGE, PACKAGE.parent)]
    roots += [(init.parent, init.parent.parent) for init in sorted(EXAMPLES.glob("*/*/__init__.py"))]
    return roots


def all_modules() -> dict[str, Path]:
    mods: dict[str, Path] = {}
    for folder, base in package_roots():
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(base).with_suffix("").parts
            mods[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return mods


def _importlib_target(node: ast.Call) -> str | None:
    """The module of ``import_module(...)``/``__import__(...)``: a literal, or an f-string's literal package
    prefix; '' when the name is not known before run time; None for other calls."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
    if name not in ("import_module", "__import__") or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
        return arg.value
    if isinstance(arg, ast.JoinedStr) and arg.values and isinstance(arg.values[0], ast.Constant):
        return str(arg.values[0].value).rsplit(".", 1)[0]
    return ""


def imported_modules(path: Path, module: str, mods: dict[str, Path]) -> Iterator[tuple[int, str]]:
    """(line, name) of every import in a module, relative ones resolved; ``from P import n`` names ``P.n``
    when that is a module; a non-literal ``import_module`` yields the name ``"?"``."""
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            yield from ((node.lineno, a.name) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            subs = [f"{name}.{a.name}" for a in node.names if f"{name}.{a.name}" in mods]
            yield from ((node.lineno, s) for s in subs)
            if len(subs) < len(node.names):
                yield node.lineno, name
        elif isinstance(node, ast.Call) and (target := _importlib_target(node)) is not None:
            yield node.lineno, target or "?"


def resolve(name: str, mods: dict[str, Path]) -> str | None:
    """The module (of this tree) an import name loads, or None for third-party names."""
    while name not in mods:
        if "." not in name:
            return None
        name = name.rsplit(".", 1)[0]
    return name


def layer_of(module: str) -> int | None:
    best: tuple[int, int] | None = None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or (module.startswith(p + ".") and p != "invphys")) and (best is None or len(p) > best[0]):
                best = (len(p), i)
    return None if best is None else best[1]


def edges() -> tuple[dict[str, set[str]], list[str]]:
    """The import graph of this tree's modules, and the files holding a non-literal ``import_module``."""
    mods = all_modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    dynamic = []
    for module, path in mods.items():
        for _, name in imported_modules(path, module, mods):
            if name == "?":
                dynamic.append(str(path.relative_to(ROOT)))
            elif (target := resolve(name, mods)) and target != module:
                graph[module].add(target)
    return graph, sorted(set(dynamic))


def _top(module: str) -> str:
    return module.split(".")[0]


def upward_imports(graph: dict[str, set[str]]) -> dict[tuple[str, str], str]:
    """Every import of a higher layer, or of an example by invphys, or between independent examples."""
    found = {}
    for src, targets in graph.items():
        for dst in targets:
            ls, ld = layer_of(src), layer_of(dst)
            if ls is None or ld is None:
                found[(src, dst)] = "a module in no layer"
            elif ld > ls:
                found[(src, dst)] = f"layer {ls} imports layer {ld}"
            elif any(_top(src) in g and _top(dst) in g and _top(src) != _top(dst) for g in SIBLINGS_APART):
                found[(src, dst)] = "one example imports another"
    return found


def circles(graph: dict[str, set[str]]) -> list[frozenset[str]]:
    """Strongly connected groups of two or more modules (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                group = set()
                while True:
                    w = stack.pop()
                    on.discard(w)
                    group.add(w)
                    if w == v:
                        break
                if len(group) > 1:
                    found.append(frozenset(group))
    return found


@pytest.fixture(scope="module")
def tree() -> tuple[dict[str, set[str]], list[str]]:
    """This tree's import graph and dynamic import sites, read once for the tests below."""
    return edges()


def test_every_module_has_a_layer(tree) -> None:
    graph, _ = tree
    assert [m for m in graph if layer_of(m) is None] == []
    assert len(graph) > 100


def test_layers_only_look_down(tree) -> None:
    graph, _ = tree
    new = {k: v for k, v in upward_imports(graph).items() if k not in KNOWN_UPWARD}
    assert new == {}


def test_known_upward_imports_still_exist(tree) -> None:
    """An entry whose import is gone must leave the list, so that it cannot come back unnoticed."""
    graph, _ = tree
    assert [k for k in KNOWN_UPWARD if k not in upward_imports(graph)] == []


def test_no_new_import_circles(tree) -> None:
    graph, _ = tree
    assert [sorted(c) for c in circles(graph) if not any(c <= known for known in KNOWN_CIRCLES)] == []


def test_known_circles_still_exist(tree) -> None:
    graph, _ = tree
    found = circles(graph)
    assert [sorted(k) for k in KNOWN_CIRCLES if not any(c <= k for c in found)] == []


STAGES = "invphys.pipeline.stages."


def stage_cross_imports(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(stage, other stage) for every import of one ``invphys.pipeline.stages`` module by another: stages share
    files through ``invphys.pipeline.stage_files`` and ``invphys.pipeline.artifacts``, not through each other."""
    return sorted((src, dst) for src, dsts in graph.items() for dst in dsts
                  if src.startswith(STAGES) and dst.startswith(STAGES) and src != dst)


def test_no_stage_imports_another_stage(tree) -> None:
    graph, _ = tree
    assert len([m for m in graph if m.startswith(STAGES)]) >= 6
    assert stage_cross_imports(graph) == []


def test_the_check_catches_a_stage_importing_a_stage(tmp_path, monkeypatch) -> None:
    """The checker itself: a lazy ``from`` import and an ``from invphys.pipeline.stages import x`` are caught."""
    stages = "invphys/pipeline/stages"
    _plant(tmp_path, {"invphys/__init__.py": "", "invphys/pipeline/__init__.py": "", f"{stages}/__init__.py": "",
                      f"{stages}/a.py": "def f():\n    from invphys.pipeline.stages.b import g\n",
                      f"{stages}/b.py": "def g():\n    from invphys.pipeline.stages import c\n",
                      f"{stages}/c.py": "from invphys.pipeline import stage_files\n",
                      "invphys/pipeline/stage_files.py": ""})
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "invphys")
    monkeypatch.setattr(sys.modules[__name__], "EXAMPLES", tmp_path / "examples")
    graph, _ = edges()
    assert stage_cross_imports(graph) == [(f"{STAGES}a", f"{STAGES}b"), (f"{STAGES}b", f"{STAGES}c")]


def test_dynamic_imports_are_the_listed_ones(tree) -> None:
    _, dynamic = tree
    assert dynamic == sorted(DYNAMIC_IMPORT_SITES)


def test_the_built_in_plugins_are_an_entry_point_above_the_registry(tree) -> None:
    """The registry imports no plugin: invphys's own ``invphys`` entry points name the built-ins, as a plugin
    distribution's do, and each names a module of a layer above the registry's."""
    graph, _ = tree
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    eps = project["entry-points"]["invphys"]
    assert eps == {"builtin": "invphys.plugins.builtin"}
    above = [v for v in eps.values() if (layer_of(v.partition(":")[0]) or 0) > (layer_of("invphys.registry") or 0)]
    assert above == list(eps.values()) and all(v.partition(":")[0] in graph for v in eps.values())
    assert not any(d.startswith("invphys.plugins") for d in graph["invphys.registry"])


def test_invphys_imports_no_example(tree) -> None:
    graph, _ = tree
    examples = {p for layer in LAYERS[-2:] for p in layer}
    assert [(s, d) for s, ds in graph.items() for d in ds if _top(s) == "invphys" and _top(d) in examples] == []


def _plant(tmp_path: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


@pytest.mark.parametrize(("source", "expected"), [
    ("from invphys.pipeline.runner import run_spec\n", ("invphys.core.x", "invphys.pipeline.runner")),
    ("def f():\n    import invphys.models.nets\n", ("invphys.core.x", "invphys.models.nets")),
    ("from .. import cli\n", ("invphys.core.x", "invphys.cli")),
    ("from invphys import plugins\n", ("invphys.core.x", "invphys.plugins")),
    ("import importlib\nimportlib.import_module('invphys.cli')\n", ("invphys.core.x", "invphys.cli")),
    ("import invphys_orange_peel\n", ("invphys.core.x", "invphys_orange_peel")),
])
def test_the_check_catches_an_upward_import(tmp_path, monkeypatch, source, expected) -> None:
    """The checker itself: a planted upward import (top-level, lazy, relative, importlib, an example)."""
    files = {f"invphys/{p}/__init__.py": "" for p in ("core", "pipeline", "models", "cli", "plugins")}
    _plant(tmp_path, {**files, "invphys/__init__.py": "", "invphys/pipeline/runner.py": "",
                      "invphys/models/nets.py": "", "invphys/core/x.py": source,
                      "examples/orange_peel/invphys_orange_peel/__init__.py": ""})
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "invphys")
    monkeypatch.setattr(sys.modules[__name__], "EXAMPLES", tmp_path / "examples")
    graph, _ = edges()
    assert list(upward_imports(graph)) == [expected]


def test_the_check_catches_a_circle_and_a_food_importing_a_food(tmp_path, monkeypatch) -> None:
    _plant(tmp_path, {"invphys/__init__.py": "", "invphys/core/__init__.py": "",
                      "invphys/core/a.py": "from invphys.core import b\n",
                      "invphys/core/b.py": "def f():\n    from invphys.core import a\n",
                      "examples/orange_peel/invphys_orange_peel/__init__.py": "import invphys_cheese_cut\n",
                      "examples/cheese_cut/invphys_cheese_cut/__init__.py": ""})
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "invphys")
    monkeypatch.setattr(sys.modules[__name__], "EXAMPLES", tmp_path / "examples")
    graph, _ = edges()
    assert circles(graph) == [frozenset({"invphys.core.a", "invphys.core.b"})]
    assert upward_imports(graph) == {("invphys_orange_peel", "invphys_cheese_cut"): "one example imports another"}
