"""Compute backends: each module holds only state and kernels and imports its library (taichi, warp) at top.

A backend implements ``load(table, friction)``, ``set_frame(dt, nsub, kin, damage_on)``, ``advance(n)``,
``frame_stats(lo, hi)``, ``kinematic_sums()``, ``read()``, ``sync()`` (and ``grid_mass()`` for checks).
:func:`load_backend` imports one lazily, so that nothing else pays for taichi or warp.
"""

from __future__ import annotations

from typing import Any

from invphys.core.errors import InvphysError, PluginLoadError, did_you_mean

BACKENDS = {"taichi": "invphys_anisompm.backends.taichi_backend:TaichiBackend",
            "warp": "invphys_anisompm.backends.warp_backend:WarpBackend"}


def load_backend(name: str) -> Any:
    """The backend class called ``name`` (imports its library now)."""
    import contextlib
    import importlib
    import sys

    if name not in BACKENDS:
        raise InvphysError(f"unknown AnisoMPM backend {name!r}.{did_you_mean(name, BACKENDS)} "
                           f"Backends: {', '.join(BACKENDS)}")
    module_name, _, cls_name = BACKENDS[name].partition(":")
    try:
        with contextlib.redirect_stdout(sys.stderr):  # keep library banners off stdout (--json)
            module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise PluginLoadError(f"the AnisoMPM {name!r} backend is not available: {exc}. "
                              f"Install it with `pip install invphys-anisompm[{name}]`") from exc
    return getattr(module, cls_name)
