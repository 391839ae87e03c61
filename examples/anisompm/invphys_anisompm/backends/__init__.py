"""Compute backends: each module holds only state and kernels and imports its library (taichi, warp) at top.

A backend implements ``load(table, friction)``, ``set_frame(dt, nsub, kin, damage_on)``, ``advance(n)``,
``frame_stats(lo, hi)``, ``kinematic_sums()``, ``read()``, ``sync()`` (and ``grid_mass()`` for checks);
continuous batching also uses ``load_slots``, ``read_slots``, ``frame_stats(lo, hi, slots)``,
``kinematic_sums(slots)`` and ``frame_end(lo, hi, slots)`` (both of those at once). Its attribute
``reads_are_new`` says whether ``read``/``read_slots`` return new host arrays that no later call changes
(then the engine keeps views of them instead of copying each run's particles). A backend may also offer
``read_slots_later(slots)``: a handle whose ``result()`` gives ``read_slots``' arrays, taken after the next
launch (:class:`ReadyRead` is the handle of a read already done).
:func:`load_backend` imports one lazily, so that nothing else pays for taichi or warp.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Any

from invphys.core.errors import InvphysError, PluginLoadError, did_you_mean

BACKENDS = {"taichi": "invphys_anisompm.backends.taichi_backend:TaichiBackend",
            "warp": "invphys_anisompm.backends.warp_backend:WarpBackend"}


class ReadyRead:
    """The handle of a read whose host arrays are already there: ``result()`` returns them."""

    def __init__(self, arrays: tuple[Any, ...]):
        self._arrays = arrays

    def result(self) -> tuple[Any, ...]:
        return self._arrays


@contextlib.contextmanager
def quiet_library() -> Iterator[None]:
    """Silence a heavy library's start-up lines (Taichi's banner and log, Warp's "initialized" and
    "could not find the CUDA driver" lines) at the file-descriptor level, so native prints are caught too
    and ``--json`` output stays clean. With ``INVPHYS_DEBUG=1`` (the CLI's ``--debug``) nothing is hidden."""
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
        raise InvphysError(f"unknown AnisoMPM backend {name!r}.{did_you_mean(name, BACKENDS)} "
                           f"Backends: {', '.join(BACKENDS)}")
    module_name, _, cls_name = BACKENDS[name].partition(":")
    try:
        with quiet_library():  # keep library banners off stdout (--json) and out of normal runs
            module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise PluginLoadError(f"the AnisoMPM {name!r} backend is not available: {exc}. "
                              f"Install it with `pip install invphys-anisompm[{name}]`") from exc
    return getattr(module, cls_name)
