"""Compute backends: each module holds only kernels and imports its library (taichi, warp) at top.

:func:`load_backend` imports a backend lazily, so that nothing else pays for taichi or warp.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Any

from invphys.core.errors import InvphysError, PluginLoadError, did_you_mean

BACKENDS = {"taichi": "invphys_orange_peel.backends.taichi_backend:TaichiBackend",
            "warp": "invphys_orange_peel.backends.warp_backend:WarpBackend"}


@contextlib.contextmanager
def quiet_library() -> Iterator[None]:
    """Silence a heavy library's start-up lines (Taichi's version banner and ``[I ...]``/``[W ...]`` log,
    Warp's "could not find the CUDA driver" warning) at the file-descriptor level, so native prints are
    caught too. With ``INVPHYS_DEBUG=1`` (the CLI's ``--debug``/``-v``) nothing is hidden."""
    if os.environ.get("INVPHYS_DEBUG", "") not in ("", "0"):
        yield
        return
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved = []
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        for fd in (1, 2):
            saved.append((fd, os.dup(fd)))
            os.dup2(devnull, fd)
        os.close(devnull)
    except OSError:  # no real descriptors (e.g. an embedded interpreter): keep going, unsilenced
        pass
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        for fd, old in saved:
            os.dup2(old, fd)
            os.close(old)


def load_backend(name: str) -> Any:
    """The backend class called ``name`` (imports its library now)."""
    import importlib

    if name not in BACKENDS:
        raise InvphysError(f"unknown orange-peel backend {name!r}.{did_you_mean(name, BACKENDS)} "
                           f"Backends: {', '.join(BACKENDS)}")
    module_name, _, cls_name = BACKENDS[name].partition(":")
    try:
        with quiet_library():  # keep library banners off stdout (--json) and out of normal runs
            module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise PluginLoadError(
            f"the orange-peel {name!r} backend is not available: {exc}. "
            f"Install it with `pip install invphys-orange-peel[{name}]`"
        ) from exc
    return getattr(module, cls_name)
