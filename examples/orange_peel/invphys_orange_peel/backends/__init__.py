"""Compute backends: each module holds only kernels and imports its library (taichi, warp) at top.

:func:`load_backend` imports a backend lazily, so that nothing else pays for taichi or warp.
"""

from __future__ import annotations

from typing import Any

from invphys.core.errors import InvphysError, PluginLoadError, did_you_mean

BACKENDS = {"taichi": "invphys_orange_peel.backends.taichi_backend:TaichiBackend",
            "warp": "invphys_orange_peel.backends.warp_backend:WarpBackend"}


def load_backend(name: str) -> Any:
    """The backend class called ``name`` (imports its library now)."""
    import contextlib
    import importlib
    import sys

    if name not in BACKENDS:
        raise InvphysError(f"unknown orange-peel backend {name!r}.{did_you_mean(name, BACKENDS)} "
                           f"Backends: {', '.join(BACKENDS)}")
    module_name, _, cls_name = BACKENDS[name].partition(":")
    try:
        with contextlib.redirect_stdout(sys.stderr):  # keep library banners off stdout (--json)
            module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise PluginLoadError(
            f"the orange-peel {name!r} backend is not available: {exc}. "
            f"Install it with `pip install invphys-orange-peel[{name}]`"
        ) from exc
    return getattr(module, cls_name)
