"""Crash-safe files: write to a temporary name, fsync, rename. A killed run never leaves half a file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np


def atomic_write_bytes(path: Path, data: bytes, tmp_name: str | None = None) -> None:
    """Write ``data`` to ``path`` atomically and durably (file and directory fsynced)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(tmp_name or f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def write_json(path: Path, data: Any, sort_keys: bool = True, indent: int | None = 2) -> None:
    """Write ``data`` as JSON (indented; ``indent=None``: compact), atomically; NumPy arrays and scalars and
    paths are converted."""
    separators = None if indent is not None else (",", ":")
    blob = json.dumps(data, indent=indent, separators=separators, sort_keys=sort_keys, default=json_default).encode()
    atomic_write_bytes(Path(path), blob)


def json_default(obj: Any) -> Any:
    """``json.dumps`` fallback for NumPy arrays/scalars, paths and anything else (as ``str``)."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return str(obj)


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def output_directory(path: str | os.PathLike[str], option: str = "--out") -> Path:
    """Create (or reuse) the output directory a user named; a file there or an unwritable place is
    a clean :class:`~invphys.core.errors.InvphysError` naming ``option``, not a traceback."""
    from invphys.core.errors import InvphysError

    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InvphysError(f"{option} {str(out)!r} is a file; name a new or existing directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InvphysError(f"cannot create {option} {str(out)!r}: {exc.strerror or exc}") from None
    return out
