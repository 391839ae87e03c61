"""Reading and classifying every part file of a store against its manifest and schema: what
:meth:`~invphys.core.dataset.DatasetStore.verify` reports, what repair acts on and what readers refuse.

A part file is never read whole before its size is checked, a symbolic link is never followed, and a part
the manifest does not list is read only when it is about as large as the listed ones."""

from __future__ import annotations

import hashlib
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from invphys.core.store.base import StoreBase
from invphys.core.store.layout import SCHEMA_KEY, STRAY_MIN_BYTES, max_part_bytes, short
from invphys.core.store.rows import table_schema

#: problems that readers through invphys tolerate (they read neither): verify and repair report them
HARMLESS = ("unlisted", "stray")


@dataclass
class PartProblem:
    """One thing wrong with a store's parts (see :meth:`DatasetStore.verify`).

    ``kind`` is ``missing`` (listed, absent), ``corrupt`` (unreadable, or bytes differ from the
    manifest), ``foreign`` (another store's or another program's rows), ``duplicate`` (rows already
    stored by another part), ``unlisted`` (a good part the manifest does not name: a writer killed
    between writing it and recording it) or ``stray`` (an entry that is no part, such as a directory
    another program wrote into the store: never read, never moved; readers through invphys ignore it,
    other Parquet readers would not).
    """

    part: str
    kind: str
    detail: str
    rows: int | None = None

    def text(self) -> str:
        rows = f", {self.rows} rows" if self.rows is not None else ""
        return f"{self.part}: {self.kind} ({self.detail}{rows})"


@dataclass
class Part:
    """A part file read and checked: its rows, checksum and size."""

    name: str
    table: Any = None
    sha256: str = ""
    nbytes: int = 0


@dataclass
class Scan:
    """What :func:`scan_store` found: the good parts (in manifest order, then unlisted ones), the problems,
    and the store's schema."""

    parts: list[Part]
    problems: list[PartProblem]
    has_manifest: bool
    schema: Any


def scan_store(store: StoreBase, use_manifest: bool = True) -> Scan:
    """Read and classify every part (see :class:`PartProblem`)."""
    meta = store.metadata
    manifest = store.manifest if use_manifest else None
    schema = table_schema(tuple(meta["param_names"]), tuple(meta["feature_names"]))
    listed = {p["name"]: p for p in manifest["parts"]} if manifest is not None else {}
    files = {p.name: p for p in store.path.glob("part-*.parquet")}
    good: list[Part] = []
    problems: list[PartProblem] = []
    seen_keys: dict[str, str] = {}
    sha_of: dict[str, str] = {}

    # a file the manifest does not list (a killed writer's part) is about as large as the listed ones
    biggest = max((p.get("bytes") for p in listed.values() if isinstance(p.get("bytes"), int)), default=0)
    stray_limit = max(STRAY_MIN_BYTES, 8 * biggest) if biggest else None

    def load(name: str, expect: dict[str, Any] | None) -> Part | None:
        data, why = _read_part(files[name], expect, stray_limit)
        if data is None:
            problems.append(PartProblem(name, "corrupt", why, expect["rows"] if expect else None))
            return None
        digest = hashlib.sha256(data).hexdigest()
        if expect is not None and (digest != expect["sha256"] or len(data) != expect.get("bytes", len(data))):
            problems.append(PartProblem(name, "corrupt", f"{len(data)} bytes that differ from the "
                                        "manifest's checksum (truncated or changed)", expect["rows"]))
            return None
        if expect is None and digest in sha_of:
            problems.append(PartProblem(name, "duplicate", f"a byte-for-byte copy of {sha_of[digest]}"))
            return None
        try:
            table = _read_parquet_bytes(data)
        except Exception as exc:
            problems.append(PartProblem(name, "corrupt", f"not readable as Parquet: {short(exc)}"))
            return None
        alien = _foreign(table, meta, schema)
        if alien:
            problems.append(PartProblem(name, "foreign", alien, table.num_rows))
            return None
        table = table.select(schema.names).cast(schema)
        keys = table.column("key").to_pylist()
        clash = [k for k in keys if k in seen_keys]
        if clash or len(set(keys)) != len(keys):
            other = seen_keys[clash[0]] if clash else name
            problems.append(PartProblem(name, "duplicate", f"{len(clash) or len(keys) - len(set(keys))} "
                                        f"row keys already stored by {other}", table.num_rows))
            return None
        sha_of[digest] = name
        return Part(name, table, digest, len(data))

    def accept(part: Part) -> None:
        good.append(part)
        seen_keys.update((k, part.name) for k in part.table.column("key").to_pylist())

    for name, entry in listed.items():
        if name not in files:
            problems.append(PartProblem(name, "missing", "listed in the manifest, file absent", entry["rows"]))
            continue
        part = load(name, entry)
        if part is not None:
            accept(part)
    for name in sorted(set(files) - set(listed)):
        part = load(name, None)
        if part is None:
            continue
        accept(part)
        if manifest is not None:
            problems.append(PartProblem(name, "unlisted", "a good part the manifest does not name",
                                        part.table.num_rows))
    problems += [PartProblem(name, "stray", "not part of the store; pandas.read_parquet(DIR) and pyarrow.dataset "
                             "would try to read it: move it out of the store") for name in _strays(store.path, files)]
    return Scan(parts=good, problems=problems, has_manifest=manifest is not None, schema=schema)


def _strays(path: Path, parts: Any) -> list[str]:
    """Entries of the store directory that are neither parts nor hidden (``.``/``_``): other readers
    (pandas, pyarrow.dataset) would read them; listed by name only, never opened."""
    return sorted(n for n in os.listdir(path) if not n.startswith((".", "_")) and n not in parts)


def part_entry(part: Part) -> dict[str, Any]:
    """The manifest's entry for a good part."""
    return {"name": part.name, "rows": int(part.table.num_rows), "bytes": part.nbytes, "sha256": part.sha256}


def problems_message(path: Path, problems: list[PartProblem]) -> str:
    """The one-line refusal of a store with bad parts (the first three named)."""
    shown = "; ".join(p.text() for p in problems[:3])
    more = f" and {len(problems) - 3} more" if len(problems) > 3 else ""
    return (f"dataset {str(path)!r} has {len(problems)} bad part(s): {shown}{more}. "
            f"`invphys dataset verify {path}` lists them; `--repair` quarantines them")


def _read_part(path: Path, expect: dict[str, Any] | None,
               stray_limit: int | None = None) -> tuple[bytes | None, str]:
    """The bytes of the part file ``path``, or None and why not; nothing is read whole before its size
    is checked: against the manifest's ``bytes`` (``expect``), and against :func:`max_part_bytes`. A file
    the manifest does not list is read only when it is at most ``stray_limit`` bytes and starts and ends
    like a Parquet file. A symbolic link is never followed."""
    try:
        st = os.lstat(path)
    except OSError as exc:
        return None, f"cannot stat it: {exc.strerror or exc}"
    if stat.S_ISLNK(st.st_mode):
        return None, "a symbolic link, not a part file (never followed)"
    if not stat.S_ISREG(st.st_mode):
        return None, "not a regular file"
    size, limit = st.st_size, max_part_bytes()
    want = expect.get("bytes") if expect is not None else None
    if isinstance(want, int) and size != want:
        return None, f"{size:,} bytes where the manifest says {want:,} (truncated or changed; not read)"
    if size > limit:
        return None, f"{size:,} bytes, over the {limit:,}-byte part limit (INVPHYS_MAX_PART_BYTES); not read"
    if expect is None and stray_limit is not None and size > stray_limit:
        return None, (f"{size:,} bytes, far more than any part the manifest lists (over {stray_limit:,}); "
                      "not read")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as fh:
            if expect is None and not _parquet_marks(fh, size):
                return None, f"{size:,} bytes that do not start and end like a Parquet file; not read"
            data = fh.read(size + 1)  # never more than the size checked above (it may grow meanwhile)
    except OSError as exc:
        return None, f"cannot read it: {exc.strerror or exc}"
    if len(data) != size:
        return None, f"changed while being read ({size:,} bytes, then {len(data):,})"
    return data, ""


def _parquet_marks(fh: Any, size: int) -> bool:
    """Whether the open file ``fh`` (of ``size`` bytes) starts and ends with ``PAR1``; rewinds it."""
    if size < 12:
        return False
    head = fh.read(4)
    fh.seek(size - 4)
    tail = fh.read(4)
    fh.seek(0)
    return bool(head == b"PAR1" and tail == b"PAR1")


def _read_parquet_bytes(data: bytes) -> Any:
    # no Arrow thread pools (parts are small): a process that exits right after starting them (a CLI
    # command failing on a bad store) aborted now and then at teardown ("terminate called without an
    # active exception", SIGABRT; measured ~12 % under load when reading with threads, 0 of 120 without)
    import pyarrow as pa
    import pyarrow.parquet as pq

    return pq.read_table(pa.BufferReader(data), use_threads=False, pre_buffer=False)


def _foreign(table: Any, meta: dict[str, Any], schema: Any) -> str | None:
    """Why ``table`` does not belong to the store described by ``meta`` (None when it does)."""
    raw = (table.schema.metadata or {}).get(SCHEMA_KEY)
    if raw is not None:
        try:
            prov = json.loads(raw)
        except ValueError:
            return "unreadable invphys provenance"
        if not isinstance(prov, dict):
            return "unreadable invphys provenance"
        for key in ("identity", "param_names", "feature_names"):
            if prov.get(key) != meta.get(key):
                return f"its {key} differs from the store's"
    missing = [n for n in schema.names if n not in table.schema.names]
    if missing:
        return f"lacks column(s) {', '.join(missing[:3])}{'...' if len(missing) > 3 else ''}"
    try:
        table.select(schema.names).cast(schema)
    except Exception as exc:
        return f"column types differ: {short(exc)}"
    return None
