"""The plugin registry: a pluggy PluginManager over the ``invphys`` entry-point group.

* The built-in plugins come as third parties' do: through the ``invphys`` entry-point group (invphys's own
  ``pyproject.toml`` names ``invphys.plugins.builtin``), so this module imports no plugin. They are loaded
  whatever the setting below; from a source tree without installed metadata (or metadata older than the
  entry point) they are read from the ``pyproject.toml`` beside the package.
* Other distributions' entry points are discovered lazily, once, on the first lookup; set
  ``INVPHYS_DISABLE_PLUGIN_AUTOLOAD=1`` to skip them (the tests do, and register what they need explicitly).
* ``"package.module:ClassName"`` works wherever a plugin name does (unpackaged code); so does
  ``"module:function"`` for a Python function described as a simulator (``invphys.simulator_from_function``,
  or a plain function whose spec block gives its ``parameters``: :mod:`invphys.plugins.simulators.function`).
  A module that is not importable but lies in the current directory is found there, as ``python -m`` would.
* Two distributions registering the same name for one kind fail at start-up, naming both.
* Unknown names answer with a did-you-mean and the installed names.

Typical use::

    from invphys import registry
    cls = registry.get("optimizer", "cma_es")
    opt = registry.create("optimizer", {"type": "cma_es", "sigma0": 0.3})
"""

from __future__ import annotations

import importlib
import os
import threading
import tomllib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Any

import pluggy

from invphys.core import hookspecs
from invphys.core.errors import (
    DuplicatePluginError,
    InvphysError,
    PluginLoadError,
    PluginNotFoundError,
    did_you_mean,
)

ENTRY_POINT_GROUP = "invphys"
AUTOLOAD_ENV = "INVPHYS_DISABLE_PLUGIN_AUTOLOAD"
BUILTIN_DISTRIBUTION = "invphys"

KINDS: tuple[str, ...] = tuple(hookspecs.HOOK_FOR_KIND)
_KIND_LABEL = {k: k.replace("_", " ") for k in KINDS}


class RegistryHooks:
    """Hooks the registry calls besides the ``invphys_register_*`` ones (:mod:`invphys.core.hookspecs`)."""

    @hookspecs.hookspec(firstresult=True)
    def invphys_plugin_for_callable(self, kind: str, obj: object, path: str) -> type | None:  # type: ignore[empty-body]
        """The plugin class of ``kind`` that a Python function ``obj`` (named ``path``, "module:function")
        gives, or None when this plugin does not make one (the built-ins: functions described as simulators,
        :func:`invphys.plugins.simulators.function.plugin_for_callable`)."""


@dataclass(frozen=True)
class PluginInfo:
    """A registered plugin class and where it came from."""

    kind: str
    name: str
    cls: type[Any]
    distribution: str
    version: str

    @property
    def qualname(self) -> str:
        return f"{self.cls.__module__}:{self.cls.__qualname__}"

    def to_dict(self) -> dict[str, str]:
        return {"kind": self.kind, "name": self.name, "distribution": self.distribution,
                "version": self.version, "class": self.qualname}


class Registry:
    """Name -> class tables per plugin kind, filled from pluggy hooks on first use."""

    def __init__(self, autoload: bool | None = None) -> None:
        self._lock = threading.RLock()
        self._autoload = autoload
        self.pm = pluggy.PluginManager(hookspecs.PROJECT)
        self.pm.add_hookspecs(hookspecs)
        self.pm.add_hookspecs(RegistryHooks)
        self._dist_of: dict[int, tuple[str, str]] = {}  # id(module/object) -> (dist, version)
        self._tables: dict[str, dict[str, PluginInfo]] | None = None
        self._loaded_entry_points = False
        self._loaded_builtins = False

    # -- registration --------------------------------------------------------------------------
    def register(self, plugin: object, distribution: str = "<local>", version: str = "",
                 name: str | None = None) -> None:
        """Register an object (usually a module) that implements ``invphys_register_*`` hooks."""
        with self._lock:
            self.pm.register(plugin, name=name)
            self._dist_of[id(plugin)] = (distribution, version)
            self._tables = None

    def unregister(self, plugin: object) -> None:
        with self._lock:
            self.pm.unregister(plugin)
            self._dist_of.pop(id(plugin), None)
            self._tables = None

    def _autoload_enabled(self) -> bool:
        if self._autoload is not None:
            return self._autoload
        return os.environ.get(AUTOLOAD_ENV, "").strip().lower() not in {"1", "true", "yes"}

    def _load_builtins(self) -> None:
        """invphys's own entry points (its built-in plugins), whatever :data:`AUTOLOAD_ENV` says (once)."""
        if self._loaded_builtins:
            return
        version = _version_of(BUILTIN_DISTRIBUTION)
        for ep in _builtin_entry_points():
            if self.pm.get_plugin(f"{BUILTIN_DISTRIBUTION}:{ep.name}") is None:
                self.register(_load(ep, BUILTIN_DISTRIBUTION), BUILTIN_DISTRIBUTION, version,
                              name=f"{BUILTIN_DISTRIBUTION}:{ep.name}")
        self._loaded_builtins = True

    def _load_entry_points(self) -> None:
        """Other distributions' entry points (once; skipped when :data:`AUTOLOAD_ENV` says so)."""
        if self._loaded_entry_points:
            return
        self._loaded_entry_points = True
        if not self._autoload_enabled():
            return
        for ep in _entry_points():
            dist = ep.dist.name if ep.dist is not None else "<unknown>"
            version = ep.dist.version if ep.dist is not None else ""
            if _is_builtin(ep) or self.pm.get_plugin(f"ep:{ep.name}") is not None:
                continue
            self.register(_load(ep, dist), dist, version, name=f"ep:{ep.name}")

    # -- tables --------------------------------------------------------------------------------
    def _build(self) -> dict[str, dict[str, PluginInfo]]:
        with self._lock:
            if self._tables is not None:
                return self._tables
            self._load_builtins()
            self._load_entry_points()
            from invphys.core.interfaces import PLUGIN_KINDS

            tables: dict[str, dict[str, PluginInfo]] = {k: {} for k in KINDS}
            for kind, hook_name in hookspecs.HOOK_FOR_KIND.items():
                hook = getattr(self.pm.hook, hook_name)
                for impl in hook.get_hookimpls():
                    dist, version = self._dist_of.get(id(impl.plugin), ("<local>", ""))
                    try:
                        classes = impl.function() or []
                    except Exception as exc:
                        raise PluginLoadError(
                            f"{hook_name} of {impl.plugin_name!r} (distribution {dist!r}) failed: "
                            f"{type(exc).__name__}: {exc}"
                        ) from exc
                    for cls in classes:
                        _check_class(cls, kind, PLUGIN_KINDS[kind], dist)
                        previous = tables[kind].get(cls.name)
                        if previous is not None and previous.cls is not cls:
                            raise DuplicatePluginError(
                                f"two {_KIND_LABEL[kind]} plugins are named {cls.name!r}: "
                                f"{previous.qualname} from distribution {previous.distribution!r} and "
                                f"{cls.__module__}:{cls.__qualname__} from distribution {dist!r}"
                            )
                        tables[kind][cls.name] = PluginInfo(kind, cls.name, cls, dist, version)
            self._tables = tables
            return tables

    def refresh(self) -> None:
        """Forget the cached tables (after registering or unregistering at run time)."""
        with self._lock:
            self._tables = None

    # -- lookup --------------------------------------------------------------------------------
    def names(self, kind: str) -> list[str]:
        return sorted(self._build()[_check_kind(kind)])

    def infos(self, kind: str | None = None) -> list[PluginInfo]:
        tables = self._build()
        kinds = [_check_kind(kind)] if kind else list(KINDS)
        return [tables[k][n] for k in kinds for n in sorted(tables[k])]

    def info(self, kind: str, name: str) -> PluginInfo:
        kind = _check_kind(kind)
        if ":" in name:
            cls = _import_path(name)
            if not isinstance(cls, type) and callable(cls):
                cls = self._plugin_for_callable(kind, cls, name)
            from invphys.core.interfaces import PLUGIN_KINDS

            _check_class(cls, kind, PLUGIN_KINDS[kind], "<local>", need_name=False)
            return PluginInfo(kind, getattr(cls, "name", name), cls, "<local>", "")
        table = self._build()[kind]
        if name in table:
            return table[name]
        label = _KIND_LABEL[kind]
        installed = ", ".join(sorted(table)) or "(none)"
        raise PluginNotFoundError(
            f"No {label} named {name!r}.{did_you_mean(name, table)} "
            f"Installed {label}s: {installed}. (`invphys plugins` lists them; "
            f"'module:Class' or 'module:function' names unpackaged code.)"
        )

    def _plugin_for_callable(self, kind: str, obj: object, path: str) -> type[Any]:
        """The class a plugin makes of the function ``obj`` (:meth:`RegistryHooks.invphys_plugin_for_callable`)."""
        self._build()  # the plugins that may turn functions into plugin classes
        made = self.pm.hook.invphys_plugin_for_callable(kind=kind, obj=obj, path=path)
        if made is None:
            raise PluginLoadError(f"{path!r} is a {type(obj).__name__}, not a {_KIND_LABEL[kind]} plugin class, "
                                  f"and no installed plugin makes one of a function")
        return made  # type: ignore[no-any-return]

    def get(self, kind: str, name: str) -> type[Any]:
        """The plugin class of ``kind`` called ``name`` (or a ``module:Class`` path)."""
        return self.info(kind, name).cls

    def create(self, kind: str, block: dict[str, Any] | str) -> Any:
        """Instantiate from a spec block ``{"type": name, **config}`` or a bare name."""
        if isinstance(block, str):
            block = {"type": block}
        settings = dict(block)
        name = settings.pop("type", None)
        if not name:
            raise InvphysError(f"a {_KIND_LABEL[_check_kind(kind)]} block needs a 'type' field")
        cls = self.get(kind, name)
        return cls(cls.Config(**settings))


def _check_kind(kind: str) -> str:
    if kind not in KINDS:
        raise PluginNotFoundError(f"unknown plugin kind {kind!r}.{did_you_mean(kind, KINDS)} "
                                  f"Kinds: {', '.join(KINDS)}")
    return kind


def _check_class(cls: Any, kind: str, base: type, dist: str, need_name: bool = True) -> None:
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise PluginLoadError(
            f"distribution {dist!r} registered {cls!r} as a {_KIND_LABEL[kind]}, but it does not "
            f"subclass {base.__module__}.{base.__name__}"
        )
    if need_name and not isinstance(getattr(cls, "name", None), str):
        raise PluginLoadError(f"{cls.__module__}:{cls.__qualname__} from distribution {dist!r} "
                              f"has no string 'name' attribute")


def _import_path(path: str) -> type[Any]:
    module_name, _, attr = path.partition(":")
    try:
        module = _import_module(module_name)
    except ImportError as exc:
        raise PluginLoadError(f"cannot import module {module_name!r} for plugin {path!r}: {exc}") from exc
    try:
        obj = module
        for part in attr.split("."):
            obj = getattr(obj, part)
    except AttributeError as exc:
        raise PluginNotFoundError(f"module {module_name!r} has no attribute {attr!r}") from exc
    return obj  # type: ignore[return-value]


def _import_module(module_name: str) -> Any:
    """``importlib.import_module``; a top-level module that is not on ``sys.path`` but lies in the current
    directory (``name.py`` or a package) is imported from there, as ``python -m`` would (the directory is
    appended to ``sys.path``, after everything installed)."""
    import sys
    from pathlib import Path

    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        top = module_name.partition(".")[0]
        cwd = Path.cwd()
        here = (cwd / f"{top}.py").is_file() or (cwd / top / "__init__.py").is_file()
        if exc.name != top or not here or str(cwd) in sys.path or "" in sys.path:
            raise
        sys.path.append(str(cwd))
        return importlib.import_module(module_name)


def _entry_points() -> Iterable[EntryPoint]:
    return entry_points(group=ENTRY_POINT_GROUP)


def _is_builtin(ep: EntryPoint) -> bool:
    name = ep.dist.name if ep.dist is not None else ""
    return name.lower().replace("_", "-") == BUILTIN_DISTRIBUTION


def _builtin_entry_points() -> list[EntryPoint]:
    """invphys's own entry points in the ``invphys`` group: from its installed metadata, else (a source
    tree on ``sys.path`` without metadata, or metadata written before the entry point) from the
    ``pyproject.toml`` beside the package. None at all is an error: nothing would be registered."""
    own = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if _is_builtin(ep)]
    if own:
        return own
    pyproject = Path(__file__).resolve().parent.parent / "pyproject.toml"
    try:
        project = tomllib.loads(pyproject.read_text()).get("project", {})
    except (OSError, tomllib.TOMLDecodeError):
        project = {}
    table = project.get("entry-points", {}).get(ENTRY_POINT_GROUP, {}) if project.get("name") == "invphys" else {}
    if not table:
        raise PluginLoadError(f"invphys's built-in plugins are not registered: the installed invphys has no "
                              f"{ENTRY_POINT_GROUP!r} entry points; reinstall it (pip install invphys, or "
                              f"pip install -e . in a checkout)")
    return [EntryPoint(name, value, ENTRY_POINT_GROUP) for name, value in sorted(table.items())]


def _load(ep: EntryPoint, dist: str) -> Any:
    """The object an entry point names; a failure is one :class:`PluginLoadError` naming it."""
    try:
        return ep.load()
    except Exception as exc:
        raise PluginLoadError(
            f"failed to load invphys plugin {ep.name!r} ({ep.value}) from distribution "
            f"{dist!r}: {type(exc).__name__}: {exc}"
        ) from exc


def _version_of(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "0+unknown"


_default: Registry | None = None
_default_lock = threading.Lock()


def default_registry() -> Registry:
    """The process-wide registry (created on first use)."""
    global _default
    with _default_lock:
        if _default is None:
            _default = Registry()
        return _default


def get(kind: str, name: str) -> type[Any]:
    """Shortcut for ``default_registry().get(kind, name)``."""
    return default_registry().get(kind, name)


def create(kind: str, block: dict[str, Any] | str) -> Any:
    """Shortcut for ``default_registry().create(kind, block)``."""
    return default_registry().create(kind, block)


def names(kind: str) -> list[str]:
    """Shortcut for ``default_registry().names(kind)``."""
    return default_registry().names(kind)


def infos(kind: str | None = None) -> list[PluginInfo]:
    """Shortcut for ``default_registry().infos(kind)``."""
    return default_registry().infos(kind)


@contextmanager
def registered(*classes: type, distribution: str = "<test>") -> Iterator[Registry]:
    """Register plugin classes on the default registry for the duration of a ``with`` block.

    Useful in tests and notebooks::

        with registry.registered(MyOptimizer):
            registry.get("optimizer", MyOptimizer.name)
    """
    from invphys.core.interfaces import PLUGIN_KINDS

    by_hook: dict[str, list[type]] = {}
    for cls in classes:
        kind = next((k for k, base in PLUGIN_KINDS.items() if issubclass(cls, base)), None)
        if kind is None:
            raise PluginLoadError(f"{cls!r} subclasses no invphys plugin interface")
        by_hook.setdefault(hookspecs.HOOK_FOR_KIND[kind], []).append(cls)

    namespace = type("_Registered", (), {})()
    for hook_name, group in by_hook.items():
        def impl(group: list[type] = group) -> list[type]:
            return group
        setattr(namespace, hook_name, hookspecs.hookimpl(impl, specname=hook_name))
    reg = default_registry()
    reg.register(namespace, distribution)
    try:
        yield reg
    finally:
        reg.unregister(namespace)
