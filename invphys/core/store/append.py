"""Appending: create (or check) a store, hold its write lock, and write rows as new parts, each written
atomically and then recorded in the manifest; a part a killed writer did not record is adopted first."""

from __future__ import annotations

import contextlib
import hashlib
import json
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Self

from invphys.core.atomic import atomic_write_bytes
from invphys.core.store.base import StoreBase
from invphys.core.store.keys import KEY_DECIMALS
from invphys.core.store.layout import (
    FORMAT,
    LOCK_FILE,
    SCHEMA_KEY,
    DatasetError,
    StoreNotWritableError,
    enclosing_store,
    max_part_bytes,
    not_writable,
    provenance,
    utcnow,
)
from invphys.core.store.rows import Row, rows_to_table
from invphys.core.store.scan import HARMLESS, part_entry, problems_message, scan_store


class Appender(StoreBase):
    """The append part of :class:`~invphys.core.dataset.DatasetStore`."""

    def create_or_check(self, metadata: dict[str, Any]) -> dict[str, Any]:
        """Create the store with ``metadata``, or check that an existing store is compatible.

        ``metadata`` must hold ``identity``, ``param_names`` and ``feature_names``; an existing store
        whose values differ raises :class:`DatasetError` (one store holds one kind of run). An existing
        store is also checked against its manifest (a part a killed writer did not record is adopted).
        Returns the store's metadata.
        """
        if not self.exists:
            if self.path.exists() and not self.path.is_dir():
                raise DatasetError(f"{str(self.path)!r} is a file; choose a new or empty directory")
            if self.path.exists() and any(p for p in self.path.iterdir() if not p.name.startswith(".")):
                raise DatasetError(f"{str(self.path)!r} exists and is not an invphys dataset; "
                                   "choose an empty or new directory")
            meta = {"format": FORMAT, "created_at": utcnow(), "key_decimals": KEY_DECIMALS,
                    "sessions": [], **metadata}
            self._write_manifest([])
            self.write_metadata(meta)
            self._keys = set()
            return meta
        meta = self.metadata
        for field_name in ("identity", "param_names", "feature_names"):
            have, want = meta.get(field_name), metadata.get(field_name)
            if have != want:
                if field_name == "identity" and isinstance(have, dict) and not have.get("config") \
                        and isinstance(want, dict) and want.get("config"):
                    raise DatasetError(
                        f"the dataset at {str(self.path)!r} was made before run identities included the "
                        "simulator's config, so its rows cannot be matched to these settings; generate into "
                        "a new directory (the old store stays readable as dataset.path)")
                raise DatasetError(
                    f"the dataset at {str(self.path)!r} holds runs with {field_name} = {have}, "
                    f"but this generation has {field_name} = {want}; write to another directory"
                )
        self._recover()
        return meta

    @contextlib.contextmanager
    def writer(self) -> Iterator[Self]:
        """Hold the store's write lock (one appending process at a time) and clear stale temp files."""
        from filelock import FileLock, Timeout

        if self.path.exists() and not self.path.is_dir():
            raise DatasetError(f"{str(self.path)!r} is a file, not a dataset directory")
        if not self.exists and self.path.is_dir() and any(not p.name.startswith(".") for p in self.path.iterdir()):
            raise DatasetError(f"{str(self.path)!r} exists and is not an invphys dataset; "
                               "choose an empty or new directory")
        outer = None if self.exists else enclosing_store(self.path)
        if outer is not None:
            raise DatasetError(f"{str(self.path)!r} is inside the dataset at {str(outer)!r} (Parquet readers of "
                               "that store would read it too); choose a directory outside it")
        lock = FileLock(str(self.path / LOCK_FILE))
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            lock.acquire(timeout=0)
        except Timeout:
            raise DatasetError(f"another process is writing to {str(self.path)!r}") from None
        except OSError as exc:
            raise StoreNotWritableError(not_writable(self.path, exc)) from None
        self._lock = lock
        try:
            try:
                for tmp in [*self.path.glob(".part-*.tmp"), *self.path.glob(".*.json.*.tmp")]:
                    tmp.unlink(missing_ok=True)  # left by a killed writer; never visible to readers
            except OSError as exc:
                raise StoreNotWritableError(not_writable(self.path, exc)) from None
            yield self
        finally:
            self._lock, self._keys = None, None
            lock.release()

    def _recover(self) -> None:
        """Under the lock: adopt good unlisted parts (a killed writer's), build a missing manifest,
        refuse any other problem; load the stored keys."""
        scan = scan_store(self)
        bad = [p for p in scan.problems if p.kind not in HARMLESS]
        if bad:
            raise DatasetError(problems_message(self.path, bad))
        if scan.problems or not scan.has_manifest:
            self._write_manifest([part_entry(p) for p in scan.parts])
        self._keys = {k for p in scan.parts for k in p.table.column("key").to_pylist()}

    def append(self, rows: Sequence[Row]) -> Path | None:
        """Write ``rows`` as one new Parquet part (atomically) and record it in the manifest.

        Needs :meth:`writer`. Returns the part's path (None if ``rows`` is empty). A key already stored
        (or repeated in ``rows``) raises :class:`DatasetError`: the store never holds a key twice.
        """
        if not rows:
            return None
        if self._lock is None:
            raise DatasetError("DatasetStore.append needs the write lock: use `with store.writer():`")
        if self._keys is None:
            self._recover()
        assert self._keys is not None
        keys = [r.key for r in rows]
        if len(set(keys)) != len(keys) or self._keys.intersection(keys):
            raise DatasetError(f"refusing to store a row key twice in {str(self.path)!r}")
        meta = self.metadata
        table = rows_to_table(rows, tuple(meta["param_names"]), tuple(meta["feature_names"]))
        return self._append_table(table, meta)

    def _append_table(self, table: Any, meta: dict[str, Any]) -> Path:
        """Write ``table`` as one part (two or more when it would exceed :func:`max_part_bytes`, so
        that readers never refuse a part this store wrote) and record it in the manifest."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        assert self._keys is not None
        manifest = self.manifest or {"parts": []}
        seq = 1 + max((int(p["name"].split("-")[1]) for p in manifest["parts"]), default=-1)
        name = f"part-{seq:06d}-{uuid.uuid4().hex[:8]}.parquet"
        table = table.replace_schema_metadata({SCHEMA_KEY: json.dumps(provenance(meta, name)).encode()})
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink, compression="zstd")
        data = sink.getvalue().to_pybytes()
        if len(data) > max_part_bytes() and table.num_rows > 1:
            half = table.num_rows // 2
            self._append_table(table.slice(0, half), meta)
            return self._append_table(table.slice(half), meta)
        atomic_write_bytes(self.path / name, data, tmp_name=f".{name}.tmp")
        entry = {"name": name, "rows": table.num_rows, "bytes": len(data),
                 "sha256": hashlib.sha256(data).hexdigest()}
        self._write_manifest([*manifest["parts"], entry])
        self._keys.update(table.column("key").to_pylist())
        return self.path / name
