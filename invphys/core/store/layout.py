"""What a dataset store's directory holds: its file names and limits, its errors, and its two JSON files
(``_metadata.json``, ``_manifest.json``), read through the bounded reader and shape-checked."""

from __future__ import annotations

import errno
import os
import re
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from invphys.core.errors import InvphysError

FORMAT = "invphys-dataset/1"
MANIFEST_FORMAT = "invphys-manifest/1"
METADATA_FILE = "_metadata.json"
MANIFEST_FILE = "_manifest.json"
QUARANTINE_DIR = "_quarantine"
LOCK_FILE = ".lock"
#: largest ``_metadata.json`` / ``_manifest.json`` read (bytes)
MAX_JSON_BYTES = 64 << 20
#: largest Parquet part written or read (bytes); ``INVPHYS_MAX_PART_BYTES`` overrides it. A part holds one
#: flushed batch (a few MB at most in practice); a larger file is refused before it is read
MAX_PART_BYTES = 1 << 30
#: a part the manifest does not list is read only up to 8 x its largest part, and at least this (bytes)
STRAY_MIN_BYTES = 64 << 20
#: Parquet schema-metadata key holding the store's provenance in each part
SCHEMA_KEY = b"invphys"
#: the name of a part file: a sequence number and a random suffix
PART_RE = re.compile(r"^part-[0-9]{6}-[0-9a-f]{8}\.parquet$")


class DatasetError(InvphysError):
    """A dataset path is missing, unreadable, locked, or incompatible with the requested simulator."""


class StoreNotWritableError(DatasetError):
    """A store that must change (repair, append) is read-only or cannot be written; nothing was changed."""


class UnsafeStoreError(DatasetError):
    """A store's layout would make a change leave the store (a symbolic-link ``_quarantine``); refused."""


def max_part_bytes() -> int:
    """The part size limit in force (:data:`MAX_PART_BYTES` or ``INVPHYS_MAX_PART_BYTES``)."""
    try:
        return max(1, int(os.environ.get("INVPHYS_MAX_PART_BYTES", MAX_PART_BYTES)))
    except ValueError:
        return MAX_PART_BYTES


def utcnow() -> str:
    """Now, in UTC, as the store's files record times."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def short(exc: BaseException) -> str:
    """An exception's message on one line of at most 160 characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def enclosing_store(path: str | os.PathLike[str]) -> Path | None:
    """The dataset store that ``path`` lies inside (the nearest parent directory, links followed, holding a
    ``_metadata.json``), or None. Nothing but a store's own files may be written there: pandas and
    pyarrow read every file of a store's directory tree."""
    p = Path(path)
    try:
        p = p.resolve()
    except (OSError, RuntimeError):   # a symbolic-link loop: judge the path as written
        p = Path(os.path.abspath(p))
    for parent in p.parents:
        try:
            if (parent / METADATA_FILE).is_file():
                return parent
        except OSError:
            continue
    return None


def read_json(path: Path) -> Any:
    """A store's JSON file through the bounded reader (:mod:`invphys.core.safe_read`: a regular file of at
    most :data:`MAX_JSON_BYTES`, UTF-8, no key twice in one object), its refusals as :class:`DatasetError`."""
    from invphys.core.safe_read import load_user_json

    try:
        return load_user_json(path, what="dataset file", max_bytes=MAX_JSON_BYTES)
    except InvphysError as exc:
        raise DatasetError(str(exc)) from None


def metadata_problem(meta: Any) -> str | None:
    """Why a parsed ``_metadata.json`` cannot describe a store (None when it can)."""
    if not isinstance(meta, dict):
        return "not a JSON object"
    for key in ("param_names", "feature_names"):
        names = meta.get(key)
        if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
            return f"{key!r} is not a non-empty list of names"
        if len(set(names)) != len(names):
            return f"{key!r} repeats a name"
    if not isinstance(meta.get("identity"), dict):
        return "'identity' is not an object"
    if "sessions" in meta and not isinstance(meta["sessions"], list):
        return "'sessions' is not a list"
    return None


def provenance(meta: dict[str, Any], part: str) -> dict[str, Any]:
    """What each part's Parquet schema metadata records (key :data:`SCHEMA_KEY`)."""
    return {"format": FORMAT, "part": part, "identity": meta.get("identity"),
            "param_names": meta.get("param_names"), "feature_names": meta.get("feature_names"),
            "simulator_block": meta.get("simulator_block"), "extractor_block": meta.get("extractor_block"),
            "written_at": utcnow()}


def not_writable(path: Path, exc: OSError, done: Sequence[str] = ()) -> str:
    """The one-line message for a store that cannot be changed (``done``: what was changed before)."""
    why = exc.strerror or str(exc)
    if exc.errno == errno.ELOOP or (os.path.islink(path) and not os.path.exists(path)):
        why = "the path is a symbolic link that leads nowhere (or in a loop)"
    elif exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        why += " (is it read-only?)"
    if done:
        return (f"cannot change the dataset at {str(path)!r}: {why}; done before that: {'; '.join(done)}; "
                f"`invphys dataset verify {path}` shows where it stands")
    return f"cannot change the dataset at {str(path)!r}: {why}; nothing was changed"
