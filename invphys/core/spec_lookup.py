"""How the spec checks find plugins without core importing the registry (a layer above it).

The checks take a :class:`PluginLookup` (anything with the registry's ``get``/``create``/``infos``); when
given none they use the process's default, which the package root installs (``invphys/__init__.py``: the
registry's ``default_registry``, imported on first use), so every ``import invphys...`` has one.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from invphys.core.errors import InvphysError


class PluginLookup(Protocol):
    """What the spec checks ask of a plugin registry (:class:`invphys.registry.Registry` is one)."""

    def get(self, kind: str, name: str) -> type[Any]: ...

    def create(self, kind: str, block: dict[str, Any] | str) -> Any: ...

    def infos(self, kind: str | None = None) -> list[Any]: ...


_default: Callable[[], PluginLookup] | None = None


def install_default(default: Callable[[], PluginLookup]) -> None:
    """Make ``default()`` the lookup of checks given none (the package root installs the registry's)."""
    global _default
    _default = default


def plugin_lookup(given: PluginLookup | None = None) -> PluginLookup:
    """``given``, else the installed default; without either, one error line (nothing to check plugins by)."""
    if given is not None:
        return given
    if _default is None:
        raise InvphysError("no plugin registry to check the spec's plugin blocks by (invphys.core.spec_lookup.install_default)")
    return _default()
