"""The plugin registry: hooks, entry points, did-you-mean, duplicates, import failures."""

from __future__ import annotations

import shutil
import subprocess
import sys
import types
import zipfile
from pathlib import Path

import pytest
from core_plugins import OtherRandomSearch, RandomSearch

from invphys import hookimpl, registry
from invphys.core.errors import DuplicatePluginError, PluginLoadError, PluginNotFoundError
from invphys.registry import Registry

ROOT = Path(__file__).resolve().parent.parent


class FakeDist:
    def __init__(self, name: str, version: str = "1.2.3") -> None:
        self.name, self.version = name, version


class FakeEntryPoint:
    """Stands in for importlib.metadata.EntryPoint (name, value, dist, load())."""

    def __init__(self, name: str, module: object, dist: str, fail: Exception | None = None) -> None:
        self.name, self.value, self.dist = name, f"{name}.plugin", FakeDist(dist)
        self._module, self._fail = module, fail

    def load(self) -> object:
        if self._fail:
            raise self._fail
        return self._module


def plugin_module(*classes: type, hook: str = "invphys_register_optimizers") -> types.ModuleType:
    mod = types.ModuleType(f"fake_{id(classes)}")

    def impl() -> list[type]:
        return list(classes)

    impl.__name__ = hook
    setattr(mod, hook, hookimpl(impl))
    return mod


def test_registered_fixture_registers_for_one_block_only():
    with registry.registered(RandomSearch):
        assert registry.get("optimizer", "test_random_search") is RandomSearch
        info = next(i for i in registry.infos("optimizer") if i.name == "test_random_search")
        assert info.distribution == "<test>"
    with pytest.raises(PluginNotFoundError):
        registry.get("optimizer", "test_random_search")


def test_entry_point_plugins_are_discovered_once_with_their_distribution(monkeypatch):
    calls = []

    def fake_eps():
        calls.append(1)
        return [FakeEntryPoint("food", plugin_module(RandomSearch), "invphys-food")]

    monkeypatch.setattr("invphys.registry._entry_points", fake_eps)
    reg = Registry(autoload=True)
    assert reg.get("optimizer", "test_random_search") is RandomSearch
    reg.names("optimizer")
    reg.refresh()
    reg.names("optimizer")
    assert len(calls) == 1
    info = reg.info("optimizer", "test_random_search")
    assert (info.distribution, info.version) == ("invphys-food", "1.2.3")


def test_autoload_can_be_turned_off_by_environment(monkeypatch):
    monkeypatch.setattr("invphys.registry._entry_points",
                        lambda: [FakeEntryPoint("food", plugin_module(RandomSearch), "invphys-food")])
    monkeypatch.setenv("INVPHYS_DISABLE_PLUGIN_AUTOLOAD", "1")
    assert "test_random_search" not in Registry().names("optimizer")
    monkeypatch.setenv("INVPHYS_DISABLE_PLUGIN_AUTOLOAD", "0")
    assert "test_random_search" in Registry().names("optimizer")


def test_duplicate_names_fail_naming_both_distributions(monkeypatch):
    monkeypatch.setattr("invphys.registry._entry_points", lambda: [
        FakeEntryPoint("a", plugin_module(RandomSearch), "dist-alpha"),
        FakeEntryPoint("b", plugin_module(OtherRandomSearch), "dist-beta"),
    ])
    with pytest.raises(DuplicatePluginError) as err:
        Registry(autoload=True).names("optimizer")
    assert "dist-alpha" in str(err.value) and "dist-beta" in str(err.value)
    assert "'test_random_search'" in str(err.value)


def test_import_failure_names_plugin_and_distribution(monkeypatch):
    monkeypatch.setattr("invphys.registry._entry_points", lambda: [
        FakeEntryPoint("broken", None, "invphys-broken", fail=ModuleNotFoundError("No module named 'zzz'")),
    ])
    with pytest.raises(PluginLoadError) as err:
        Registry(autoload=True).names("optimizer")
    msg = str(err.value)
    assert "'broken'" in msg and "invphys-broken" in msg and "zzz" in msg


def test_unknown_name_did_you_mean_and_installed_list():
    with registry.registered(RandomSearch), pytest.raises(PluginNotFoundError) as err:
        registry.get("optimizer", "test_random_serch")
    msg = str(err.value)
    assert msg.startswith("No optimizer named 'test_random_serch'. Did you mean 'test_random_search'?")
    assert "Installed optimizers:" in msg and "test_random_search" in msg


def test_module_class_escape_hatch_and_wrong_base():
    assert registry.get("optimizer", "core_plugins:RandomSearch") is RandomSearch
    with pytest.raises(PluginLoadError, match="does not subclass"):
        registry.get("surrogate", "core_plugins:RandomSearch")
    with pytest.raises(PluginLoadError, match="cannot import module"):
        registry.get("optimizer", "no_such_module_xyz:Thing")


def test_module_function_escape_hatch_finds_functions_in_the_current_directory(tmp_path, monkeypatch):
    """``module:function`` names a Python function (a simulator when its block gives parameters); a module
    that is not importable but lies in the current directory is imported from there (as ``python -m``)."""
    (tmp_path / "h7_cwd_fn.py").write_text("import numpy as np\n\ndef f(theta):\n    return np.asarray(theta) * 2\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    try:
        sim = registry.create("simulator", {"type": "h7_cwd_fn:f", "parameters": {"x": [0, 1]}, "vectorised": True})
        assert sys.path[-1] == str(tmp_path)  # appended: it never shadows an installed module
        assert sim.simulate([[0.25]])[0].trajectory.series["features"].values.tolist() == [[0.5]]
        with pytest.raises(PluginLoadError, match="not an optimizer plugin class"):
            registry.get("optimizer", "h7_cwd_fn:f")
    finally:
        sys.modules.pop("h7_cwd_fn", None)
    with pytest.raises(PluginLoadError, match="builtin_function_or_method"):
        registry.get("simulator", "os:getcwd")  # only pure-Python functions of the module named
    with pytest.raises(PluginLoadError, match="cannot import module"):
        registry.get("simulator", "no_such_module_h7:f")


def test_create_validates_config():
    opt = registry.create("optimizer", {"type": "core_plugins:RandomSearch", "sigma0": 0.5})
    assert opt.config.sigma0 == 0.5
    with pytest.raises(Exception, match="greater than 0"):
        registry.create("optimizer", {"type": "core_plugins:RandomSearch", "sigma0": -1})


def test_registering_a_non_plugin_class_is_an_error(monkeypatch):
    monkeypatch.setattr("invphys.registry._entry_points",
                        lambda: [FakeEntryPoint("bad", plugin_module(dict), "invphys-bad")])
    with pytest.raises(PluginLoadError, match="invphys-bad"):
        Registry(autoload=True).names("optimizer")


def test_listing_plugins_imports_no_heavy_library():
    code = ("import sys, invphys.registry as r; r.infos(); "
            "heavy = [m for m in ('torch', 'taichi', 'warp', 'stable_baselines3', 'ray', 'optuna', 'sqlalchemy') "
            "if m in sys.modules]; "
            "print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def _builtin_entry_point(dist: str = "invphys") -> object:
    from importlib.metadata import EntryPoint

    class Dist:
        name, version = dist, "9.9"

    ep = EntryPoint("builtin", "invphys.plugins.builtin", "invphys")
    object.__setattr__(ep, "dist", Dist())  # as importlib.metadata sets it for an installed distribution
    return ep


def test_the_built_ins_come_through_invphys_own_entry_point_even_with_autoload_off(monkeypatch):
    """The registry imports no plugin: the built-ins are invphys's entry point (installed metadata)."""
    from invphys.plugins import builtin

    monkeypatch.setenv("INVPHYS_DISABLE_PLUGIN_AUTOLOAD", "1")
    monkeypatch.setattr("invphys.registry.entry_points", lambda group: [_builtin_entry_point()])
    reg = Registry()
    assert "cma_es" in reg.names("optimizer") and "local" in reg.names("executor")
    assert reg.pm.get_plugin("invphys:builtin") is builtin
    assert reg.info("optimizer", "cma_es").distribution == "invphys"


def test_without_installed_metadata_the_built_ins_come_from_the_source_tree_pyproject(monkeypatch):
    """A source tree on sys.path (no metadata, or metadata older than the entry point): pyproject.toml says."""
    monkeypatch.setattr("invphys.registry.entry_points", lambda group: [])
    reg = Registry(autoload=False)
    assert "cma_es" in reg.names("optimizer")
    assert reg.pm.get_plugin("invphys:builtin") is not None


def test_no_built_in_entry_point_anywhere_is_one_error_line(monkeypatch, tmp_path):
    monkeypatch.setattr("invphys.registry.entry_points", lambda group: [])
    monkeypatch.setattr("invphys.registry.__file__", str(tmp_path / "invphys" / "registry.py"))
    with pytest.raises(PluginLoadError) as err:
        Registry(autoload=False).names("optimizer")
    assert "built-in plugins are not registered" in str(err.value) and "\n" not in str(err.value)


def test_a_function_needs_a_plugin_that_makes_plugins_of_functions(monkeypatch):
    """``module:function`` goes through the invphys_plugin_for_callable hook (the built-ins implement it):
    without them, a function is refused in one line."""
    reg = Registry(autoload=False)
    monkeypatch.setattr(reg, "_load_builtins", lambda: None)
    with pytest.raises(PluginLoadError, match="no installed plugin makes one of a function") as err:
        reg.get("simulator", "os.path:join")
    assert "\n" not in str(err.value)


def test_the_invphys_wheel_declares_its_built_in_plugins_as_an_entry_point(tmp_path: Path) -> None:
    pytest.importorskip("setuptools")
    """The registry finds the built-ins through this entry point (it imports no plugin itself)."""
    src = tmp_path / "invphys"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "invphys", src / "invphys", ignore=shutil.ignore_patterns("__pycache__"))
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                          "--no-index", "-w", str(tmp_path / "dist"), str(src)], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    (wheel,) = (tmp_path / "dist").glob("invphys-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        (entry,) = [n for n in zf.namelist() if n.endswith(".dist-info/entry_points.txt")]
        text = zf.read(entry).decode()
    assert "[invphys]\nbuiltin = invphys.plugins.builtin\n" in text
