"""The dataset store: append-only, crash-safe Parquet parts, a manifest, and a JSON metadata file.

A store is a directory::

    DIR/_metadata.json                 provenance, parameter space, feature names, sessions, totals
    DIR/_manifest.json                 every committed part: name, rows, bytes, sha256
    DIR/part-000000-1a2b3c4d.parquet   one part per flushed batch of rows (never rewritten)
    DIR/part-000001-....parquet
    DIR/_quarantine/                   parts set aside by ``invphys dataset verify --repair``
    DIR/.lock                          held by the one process appending

``pandas.read_parquet(DIR)``, ``pyarrow.dataset.dataset(DIR)``, polars and duckdb read every row (files and
folders starting with ``.`` or ``_`` are skipped). Each part is written under a temporary name, fsynced and
renamed atomically, then recorded in the manifest (also atomically), so a reader never sees half a part
and a killed writer loses only the rows it had not flushed. Each part's Parquet schema metadata carries
the store's provenance (key ``invphys``).

Every row carries a key: a stable hash of its normalised parameters (rounded to :data:`KEY_DECIMALS`
decimals) and the :class:`RunIdentity` (simulator name, preset, backend, version and a hash of its full
config). A re-run skips the keys already present, so it resumes instead of duplicating; a key is never
stored twice. Readers through this API check the store against its manifest on every open and refuse
(naming them) missing, corrupt, foreign or duplicated parts; :meth:`DatasetStore.verify` lists them and
:meth:`DatasetStore.repair` quarantines them and rebuilds the manifest.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import stat
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.atomic import atomic_write_bytes, write_json
from invphys.core.errors import InvphysError
from invphys.core.results import SimulationResult

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
KEY_DECIMALS = 10
#: row columns besides theta_*, p_* and f_* (in order)
META_COLUMNS: tuple[str, ...] = ("status", "failure", "wall_time_s", "substeps", "simulator",
                                 "simulator_version", "preset", "backend", "device", "created_at")
MAX_REASON_CHARS = 500


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


@dataclass(frozen=True)
class RunIdentity:
    """What, besides the parameters, makes two simulation runs the same run (part of each row key).

    ``config`` is a hash of the simulator's whole ``Config`` (:func:`config_hash`), so rows made with
    other settings are never reused; fields a simulator lists in its ``identity_ignores`` class
    attribute (e.g. the device) do not count. An empty ``config`` gives the keys of stores made before
    the config was part of the identity.
    """

    simulator: str
    preset: str = ""
    backend: str = ""
    version: str = ""
    config: str = ""

    @classmethod
    def of(cls, simulator: Any) -> RunIdentity:
        """The identity of a :class:`~invphys.core.interfaces.Simulator` instance."""
        cfg = getattr(simulator, "config", None)
        return cls(simulator=str(simulator.name), preset=str(getattr(cfg, "preset", "") or ""),
                   backend=str(getattr(cfg, "backend", "") or ""), version=str(simulator.version),
                   config=config_hash(cfg, getattr(simulator, "identity_ignores", ())))

    def to_dict(self) -> dict[str, str]:
        return {"simulator": self.simulator, "preset": self.preset, "backend": self.backend,
                "version": self.version, "config": self.config}


def extractor_identity(extractor: Any) -> dict[str, Any]:
    """What makes a feature extractor's output the same: its registered name, version, feature names
    and config hash - not how a spec named it (``orange_peel`` or a ``module:Class`` path), so memos of
    features made on one machine are found on another."""
    return {"extractor": str(getattr(extractor, "name", type(extractor).__name__)),
            "version": str(getattr(extractor, "version", "") or ""),
            "features": list(extractor.feature_names),
            "config": config_hash(getattr(extractor, "config", None))}


def config_hash(config: Any, ignore: Sequence[str] = ()) -> str:
    """A stable 16-hex-digit hash of a pydantic config's JSON dump (minus ``ignore``); ``""`` for None."""
    if config is None:
        return ""
    dump = config.model_dump(mode="json") if hasattr(config, "model_dump") else dict(config)
    dump = {k: v for k, v in dump.items() if k not in set(ignore)}
    blob = json.dumps(dump, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def round_theta(theta: np.ndarray) -> np.ndarray:
    """Normalised parameters rounded to the key precision (what the store keeps and keys)."""
    return np.round(np.clip(np.asarray(theta, dtype=np.float64), 0.0, 1.0), KEY_DECIMALS) + 0.0


def row_key(theta_row: Sequence[float] | np.ndarray, identity: RunIdentity) -> str:
    """The stable key of one run: sha256 over fixed-precision text, first 24 hex digits.

    Text (not float bits) makes it identical across processes, machines and NumPy versions.
    """
    values = ",".join(f"{v:.{KEY_DECIMALS}f}" for v in round_theta(np.asarray(theta_row)).ravel())
    text = f"{identity.simulator}|{identity.preset}|{identity.backend}|{identity.version}|{values}"
    if identity.config:
        text += f"|config={identity.config}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def row_keys(theta: np.ndarray, identity: RunIdentity) -> list[str]:
    """Keys of every row of ``theta`` (B, d)."""
    return [row_key(row, identity) for row in np.atleast_2d(theta)]


def keys_fingerprint(keys: Sequence[str]) -> str:
    """A short stable hash of a set of row keys (order does not matter)."""
    return hashlib.sha256("\n".join(sorted(keys)).encode()).hexdigest()[:16]


@dataclass
class DatasetArrays:
    """A dataset as arrays, rows sorted by key (a fixed order, independent of completion order).

    ``theta`` (N, d) normalised, ``params`` (N, d) physical, ``y`` (N, M) features (NaN in failed rows),
    ``ok`` (N,) bool, ``keys`` (N,) row keys, ``fingerprint`` a hash of the keys.
    """

    theta: np.ndarray
    y: np.ndarray
    params: np.ndarray
    param_names: tuple[str, ...]
    feature_names: tuple[str, ...]
    keys: np.ndarray
    fingerprint: str
    ok: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def __len__(self) -> int:
        return int(self.theta.shape[0])


@dataclass
class Row:
    """One finished run, ready to be stored."""

    key: str
    sample_index: int
    theta: np.ndarray
    params: np.ndarray
    result: SimulationResult


def check_features(result: SimulationResult, n_features: int) -> SimulationResult:
    """Mark ``result`` failed (in place) when it claims success without ``n_features`` finite features."""
    if not result.ok:
        return result
    f = None if result.features is None else np.asarray(result.features, dtype=np.float64).ravel()
    why = None
    if f is None:
        why = "no features"
    elif f.shape != (n_features,):
        why = f"{f.size} features, expected {n_features}"
    elif not np.isfinite(f).all():
        why = "non-finite features"
    if why is not None:
        result.ok, result.failure, result.features = False, f"features: {why}", None
    return result


def failure_reason(exc: BaseException) -> str:
    """The text stored for an exception that escaped a simulation."""
    text = f"{type(exc).__name__}: {exc}".strip()
    return text[:MAX_REASON_CHARS]


def _utcnow() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


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
class VerifyReport:
    """What :meth:`DatasetStore.verify` found (JSON-ready through :meth:`to_dict`)."""

    path: str
    parts: int
    rows: int
    problems: list[PartProblem]
    has_manifest: bool = True
    actions: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and self.has_manifest

    def to_dict(self) -> dict[str, Any]:
        return {"path": self.path, "ok": self.ok, "parts": self.parts, "rows": self.rows,
                "has_manifest": self.has_manifest, "problems": [asdict(p) for p in self.problems],
                "actions": self.actions}


@dataclass
class _Part:
    name: str
    table: Any = None
    sha256: str = ""
    nbytes: int = 0


class DatasetStore:
    """An append-only store of simulation rows in ``path`` (see the module docstring)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._lock: Any = None
        self._keys: set[str] | None = None

    def __repr__(self) -> str:
        return f"DatasetStore({str(self.path)!r})"

    # -- metadata ------------------------------------------------------------------------------
    @property
    def metadata_path(self) -> Path:
        return self.path / METADATA_FILE

    @property
    def manifest_path(self) -> Path:
        return self.path / MANIFEST_FILE

    @property
    def exists(self) -> bool:
        return self.metadata_path.is_file()

    @property
    def metadata(self) -> dict[str, Any]:
        """The parsed, shape-checked ``_metadata.json`` (:class:`DatasetError` when absent or malformed)."""
        if self.path.exists() and not self.path.is_dir():
            raise DatasetError(f"{str(self.path)!r} is a file, not a dataset directory")
        if not self.exists:
            hint = " (it has Parquet files but no _metadata.json)" if self.parts() else ""
            raise DatasetError(f"no invphys dataset at {str(self.path)!r}{hint}")
        meta = _read_json(self.metadata_path)
        problem = _metadata_problem(meta)
        if problem:
            raise DatasetError(f"{self.metadata_path} is malformed: {problem}")
        return meta

    def write_metadata(self, metadata: dict[str, Any]) -> None:
        """Replace ``_metadata.json`` atomically (temp file, fsync, rename)."""
        self.path.mkdir(parents=True, exist_ok=True)
        data = dict(metadata, updated_at=_utcnow())
        write_json(self.metadata_path, data)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(self.metadata["param_names"])

    @property
    def feature_names(self) -> tuple[str, ...]:
        return tuple(self.metadata["feature_names"])

    @property
    def manifest(self) -> dict[str, Any] | None:
        """The parsed ``_manifest.json``, or None for a store written before manifests existed."""
        if not self.manifest_path.exists():
            return None
        data = _read_json(self.manifest_path)
        parts = data.get("parts") if isinstance(data, dict) else None
        if not isinstance(parts, list) or not all(
                isinstance(p, dict) and isinstance(p.get("name"), str) and _PART_RE.match(p["name"])
                and isinstance(p.get("sha256"), str) and isinstance(p.get("rows"), int) for p in parts):
            raise DatasetError(f"{self.manifest_path} is malformed; `invphys dataset verify {self.path} --repair` "
                               "rebuilds it from the parts")
        return data

    def _write_manifest(self, parts: list[dict[str, Any]]) -> None:
        write_json(self.manifest_path, {"format": MANIFEST_FORMAT, "parts": parts,
                                        "rows": int(sum(p["rows"] for p in parts)), "updated_at": _utcnow()})

    # -- writing -------------------------------------------------------------------------------
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
            meta = {"format": FORMAT, "created_at": _utcnow(), "key_decimals": KEY_DECIMALS,
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
    def writer(self) -> Iterator[DatasetStore]:
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
            raise StoreNotWritableError(_not_writable(self.path, exc)) from None
        self._lock = lock
        try:
            try:
                for tmp in [*self.path.glob(".part-*.tmp"), *self.path.glob(".*.json.*.tmp")]:
                    tmp.unlink(missing_ok=True)  # left by a killed writer; never visible to readers
            except OSError as exc:
                raise StoreNotWritableError(_not_writable(self.path, exc)) from None
            yield self
        finally:
            self._lock, self._keys = None, None
            lock.release()

    def _recover(self) -> None:
        """Under the lock: adopt good unlisted parts (a killed writer's), build a missing manifest,
        refuse any other problem; load the stored keys."""
        scan = self._scan()
        bad = [p for p in scan.problems if p.kind not in _HARMLESS]
        if bad:
            raise DatasetError(_problems_message(self.path, bad))
        if scan.problems or not scan.has_manifest:
            self._write_manifest([_entry(p) for p in scan.parts])
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

    def content_fingerprint(self, first_ok: int | None = None) -> str:
        """A cheap hash of what the store holds now: its manifest's checksums (or, for a store without
        a manifest, each part's name, size and modification time). Changes when rows are added or lost.

        With ``first_ok``, the hash of the store's first ``first_ok`` ok rows in store order (the rows
        :meth:`arrays` gives with the same ``first_ok``): of the parts up to the one holding the last of
        them (plus the count when that part holds more ok rows), so parts appended later leave it
        unchanged. Finding that part reads the ``status`` column of the parts before it, nothing else.
        When those parts hold exactly ``first_ok`` ok rows it equals the fingerprint the store had when
        they were all it held. Raises :class:`DatasetError` when the store holds fewer ok rows.
        """
        _check_first_ok(first_ok)
        if not self.exists:
            return "absent"
        try:
            manifest = self.manifest
        except DatasetError:
            manifest = None
        if manifest is not None:
            entries = [(str(p["name"]), f"{p['name']}:{p['sha256']}") for p in manifest["parts"]]
        else:
            entries = [(p.name, f"{p.name}:{p.stat().st_size}:{p.stat().st_mtime_ns}") for p in self.parts()]
        extra: list[str] = []
        if first_ok is not None:
            held = 0
            for i, (name, _) in enumerate(entries):
                held += self._part_ok_rows(name)
                if held >= first_ok:
                    entries = entries[:i + 1]
                    break
            else:
                raise DatasetError(_too_few_message(self.path, held, first_ok))
            extra = [] if held == first_ok else [f"first {first_ok} ok rows"]
        items = sorted(item for _, item in entries) + extra
        return hashlib.sha256("\n".join(items).encode()).hexdigest()[:16]

    def _part_ok_rows(self, name: str) -> int:
        """How many ok rows the part file ``name`` holds (its ``status`` column alone is read)."""
        import pyarrow.compute as pc
        import pyarrow.parquet as pq

        try:
            if not stat.S_ISREG(os.lstat(self.path / name).st_mode):
                raise OSError("not a regular file")
            status = pq.read_table(self.path / name, columns=["status"], use_threads=False,
                                   pre_buffer=False).column("status")
        except Exception as exc:  # missing or corrupt: the reader names it (and how to repair it)
            raise DatasetError(f"dataset {str(self.path)!r}: cannot read part {name}: {_short(exc)}; "
                               f"`invphys dataset verify {self.path}` checks the store") from None
        return int(pc.sum(pc.equal(status, "ok")).as_py() or 0)

    # -- integrity -----------------------------------------------------------------------------
    def verify(self) -> VerifyReport:
        """Check every part against the manifest and the store's schema; nothing is changed. Damage is
        reported, not raised: a malformed manifest is a problem of ``_manifest.json`` (the parts are then
        checked on their own); only a path that holds no readable store raises :class:`DatasetError`."""
        try:
            scan = self._scan()
        except DatasetError as exc:
            if not self.manifest_path.exists() or _metadata_problem(self.metadata):
                raise
            scan = self._scan(use_manifest=False)
            scan.problems.insert(0, PartProblem(MANIFEST_FILE, "corrupt", f"{_short(exc)}"))
        return VerifyReport(path=str(self.path), parts=len(scan.parts),
                            rows=sum(p.table.num_rows for p in scan.parts), problems=scan.problems,
                            has_manifest=scan.has_manifest)

    def repair(self) -> VerifyReport:
        """Move corrupt/foreign/duplicate parts' files to ``_quarantine/``, drop missing ones from the
        manifest, adopt good unlisted parts, and rewrite the manifest from what remains. Returns the
        report, with ``actions``.

        Files move only by renaming inside the store directory: a ``_quarantine`` that is a symbolic
        link (or not a directory) raises :class:`UnsafeStoreError`, a store that cannot be written
        :class:`StoreNotWritableError`; either before anything changed. A symbolic-link part is moved
        as the link itself, never its target."""
        qdir = self.path / QUARANTINE_DIR
        _check_quarantine(qdir)
        if not self.exists:
            _ = self.metadata  # raises the reader's message (no store, or a file); nothing is created
        with self.writer():
            actions: list[str] = []
            try:
                scan = self._scan()
            except DatasetError:
                if not self.manifest_path.exists() or _metadata_problem(self.metadata):
                    raise
                scan = self._scan(use_manifest=False)  # a malformed manifest: rebuilt from the parts
                actions.append("replaced the malformed manifest")
            if not scan.problems and scan.has_manifest and not actions:
                return self.verify()
            _probe_writable(self.path)
            try:
                for problem in scan.problems:
                    if problem.kind == "missing":
                        actions.append(f"dropped {problem.part} from the manifest (file missing)")
                    elif problem.kind == "unlisted":
                        actions.append(f"adopted {problem.part} into the manifest")
                    elif problem.kind == "stray":
                        actions.append(f"left {problem.part} in place (not the store's to move: move it out)")
                    else:
                        _quarantine(self.path, qdir, problem.part)
                        actions.append(f"moved {problem.part} ({problem.kind}) to {QUARANTINE_DIR}/")
                self._write_manifest([_entry(p) for p in scan.parts])
            except OSError as exc:
                raise StoreNotWritableError(_not_writable(self.path, exc, actions)) from None
            if not scan.has_manifest and not actions:
                actions.append("wrote a manifest")
            report = self.verify()
            report.actions = actions
            return report

    def _scan(self, use_manifest: bool = True) -> _Scan:
        """Read and classify every part (see :class:`PartProblem`)."""
        meta = self.metadata
        manifest = self.manifest if use_manifest else None
        schema = table_schema(tuple(meta["param_names"]), tuple(meta["feature_names"]))
        listed = {p["name"]: p for p in manifest["parts"]} if manifest is not None else {}
        files = {p.name: p for p in self.path.glob("part-*.parquet")}
        good: list[_Part] = []
        problems: list[PartProblem] = []
        seen_keys: dict[str, str] = {}
        sha_of: dict[str, str] = {}

        # a file the manifest does not list (a killed writer's part) is about as large as the listed ones
        biggest = max((p.get("bytes") for p in listed.values() if isinstance(p.get("bytes"), int)), default=0)
        stray_limit = max(STRAY_MIN_BYTES, 8 * biggest) if biggest else None

        def load(name: str, expect: dict[str, Any] | None) -> _Part | None:
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
                problems.append(PartProblem(name, "corrupt", f"not readable as Parquet: {_short(exc)}"))
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
            return _Part(name, table, digest, len(data))

        def accept(part: _Part) -> None:
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
                                 "would try to read it: move it out of the store") for name in _strays(self.path, files)]
        return _Scan(parts=good, problems=problems, has_manifest=manifest is not None, schema=schema)

    # -- reading -------------------------------------------------------------------------------
    def parts(self) -> list[Path]:
        """The Parquet part files present, in write order (listed or not)."""
        if not self.path.is_dir():
            return []
        return sorted(p for p in self.path.glob("part-*.parquet") if p.is_file() and not p.is_symlink())

    def _table(self) -> Any:
        """Every stored row as one Arrow table, after checking the store (refuses any problem but an
        unlisted good part, whose rows are not read)."""
        scan = self._scan()
        bad = [p for p in scan.problems if p.kind not in _HARMLESS]
        if bad:
            raise DatasetError(_problems_message(self.path, bad))
        parts = [p.table for p in scan.parts if p.name not in {q.part for q in scan.problems}]
        import pyarrow as pa

        return pa.concat_tables(parts) if parts else scan.schema.empty_table()

    def keys(self) -> set[str]:
        """Keys of every stored row (ok and failed)."""
        return set(self._table().column("key").to_pylist())

    def ok_count(self) -> int:
        """How many ok rows the store holds (the store is checked first)."""
        import pyarrow.compute as pc

        return int(pc.sum(pc.equal(self._table().column("status"), "ok")).as_py() or 0)

    def frame(self, ok_only: bool = False, first_ok: int | None = None) -> Any:
        """All rows as a pandas DataFrame sorted by key (the store is checked first).

        ``first_ok``: only the rows stored up to the ``first_ok``-th ok row, in store order (parts in
        write order, rows in each part in order): the rows the store held when it held ``first_ok``
        ok rows, since stores only append. Raises :class:`DatasetError` when it holds fewer.
        """
        import pandas as pd

        _check_first_ok(first_ok)
        df: pd.DataFrame = self._table().to_pandas(use_threads=False)
        if first_ok is not None:
            ok_at = np.flatnonzero((df["status"] == "ok").to_numpy(dtype=bool))
            if len(ok_at) < first_ok:
                raise DatasetError(_too_few_message(self.path, len(ok_at), first_ok))
            df = df.iloc[:int(ok_at[first_ok - 1]) + 1]
        df = df.sort_values("key", kind="stable").reset_index(drop=True)
        if ok_only:
            df = df[df["status"] == "ok"].reset_index(drop=True)
        return df

    def arrays(self, ok_only: bool = True, first_ok: int | None = None) -> DatasetArrays:
        """The rows as :class:`DatasetArrays` (only successful runs unless ``ok_only=False``; only the
        store's first ``first_ok`` ok rows when given, see :meth:`frame`)."""
        meta = self.metadata
        pnames, fnames = tuple(meta["param_names"]), tuple(meta["feature_names"])
        df = self.frame(ok_only=ok_only, first_ok=first_ok)
        keys = df["key"].to_numpy(dtype=object)

        def block(prefix: str, names: tuple[str, ...]) -> np.ndarray:
            cols = [f"{prefix}{n}" for n in names]
            return df[cols].to_numpy(dtype=np.float64, na_value=np.nan).reshape(len(df), len(cols))

        return DatasetArrays(theta=block("theta_", pnames), y=block("f_", fnames), params=block("p_", pnames),
                             param_names=pnames, feature_names=fnames, keys=keys,
                             fingerprint=keys_fingerprint(list(keys)),
                             ok=(df["status"] == "ok").to_numpy(dtype=bool))

    def info(self) -> dict[str, Any]:
        """A JSON-ready summary: counts, failures by reason, provenance, feature percentiles and, for an
        adaptive design, its settings and rounds (``design``; None otherwise)."""
        from invphys.core.adaptive import describe_design

        meta = self.metadata
        df = self.frame()
        manifest = self.manifest
        ok = df[df["status"] == "ok"]
        failed = df[df["status"] != "ok"]
        reasons = failed["failure"].fillna("(no reason)").value_counts()
        features: dict[str, dict[str, float | None]] = {}
        for name in meta["feature_names"]:
            col = ok[f"f_{name}"].to_numpy(dtype=np.float64, na_value=np.nan)
            if len(col) and np.isfinite(col).any():
                p5, p50, p95 = np.nanpercentile(col, [5, 50, 95])
                features[name] = {"p5": float(p5), "p50": float(p50), "p95": float(p95)}
            else:
                features[name] = {"p5": None, "p50": None, "p95": None}
        wall = df["wall_time_s"].to_numpy(dtype=np.float64)
        sessions = meta.get("sessions", [])
        return {
            "path": str(self.path),
            "rows": len(df), "ok": len(ok), "failed": len(failed),
            "parts": len(manifest["parts"]) if manifest is not None else len(self.parts()),
            "manifest": manifest is not None,
            "failures_by_reason": {str(k): int(v) for k, v in reasons.items()},
            "identity": meta.get("identity"),
            "simulator": meta.get("simulator"),
            "extractor": meta.get("extractor_block"),
            "param_names": meta["param_names"], "feature_names": meta["feature_names"],
            "devices": sorted(set(df["device"].dropna().astype(str)) - {""}),
            "backends": sorted(set(df["backend"].dropna().astype(str)) - {""}),
            "sim_time_s": {"mean": float(wall.mean()) if len(wall) else None,
                           "total": float(wall.sum())},
            "generation_wall_s": float(sum(s.get("wall_s", 0.0) for s in sessions)),
            "sessions": len(sessions),
            "fingerprint": keys_fingerprint(list(ok["key"])),
            "features": features,
            "created_at": meta.get("created_at"), "updated_at": meta.get("updated_at"),
            "design": describe_design(self.path),
        }


@dataclass
class _Scan:
    parts: list[_Part]
    problems: list[PartProblem]
    has_manifest: bool
    schema: Any


_PART_RE = re.compile(r"^part-[0-9]{6}-[0-9a-f]{8}\.parquet$")
#: problems that readers through invphys tolerate (they read neither): verify and repair report them
_HARMLESS = ("unlisted", "stray")


def _strays(path: Path, parts: Any) -> list[str]:
    """Entries of the store directory that are neither parts nor hidden (``.``/``_``): other readers
    (pandas, pyarrow.dataset) would read them; listed by name only, never opened."""
    return sorted(n for n in os.listdir(path) if not n.startswith((".", "_")) and n not in parts)


def _entry(part: _Part) -> dict[str, Any]:
    return {"name": part.name, "rows": int(part.table.num_rows), "bytes": part.nbytes, "sha256": part.sha256}


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


def _check_quarantine(qdir: Path) -> None:
    """Refuse a ``_quarantine`` that is a symbolic link or not a directory (moves would leave the store)."""
    if os.path.islink(qdir):
        raise UnsafeStoreError(f"{qdir} is a symbolic link; repair moves files only inside the store: "
                               f"remove the link (or make {QUARANTINE_DIR} a directory) and repair again")
    if os.path.lexists(qdir) and not os.path.isdir(qdir):
        raise UnsafeStoreError(f"{qdir} is not a directory; move it away and repair again")


def _quarantine(store: Path, qdir: Path, name: str) -> None:
    """Rename the store's entry ``name`` (a link as the link itself) into ``qdir``, never replacing a file
    there; both directories are opened without following links, so nothing leaves the store."""
    if not os.path.lexists(qdir):
        os.mkdir(qdir)
    _check_quarantine(qdir)
    src_fd = os.open(store, os.O_RDONLY | os.O_DIRECTORY)
    try:
        dst_fd = os.open(qdir, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_NOFOLLOW", 0))
        try:
            target = name
            while os.path.lexists(qdir / target):
                target = f"{name}.{uuid.uuid4().hex[:6]}"
            os.rename(name, target, src_dir_fd=src_fd, dst_dir_fd=dst_fd)
        finally:
            os.close(dst_fd)
    finally:
        os.close(src_fd)


def _probe_writable(path: Path) -> None:
    """Raise :class:`StoreNotWritableError` unless a file can be created (and removed) in ``path``."""
    probe = path / f".part-probe-{uuid.uuid4().hex[:8]}.tmp"  # a writer clears any left behind
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        os.unlink(probe)
    except OSError as exc:
        raise StoreNotWritableError(_not_writable(path, exc)) from None


def _not_writable(path: Path, exc: OSError, done: Sequence[str] = ()) -> str:
    why = exc.strerror or str(exc)
    if exc.errno == errno.ELOOP or (os.path.islink(path) and not os.path.exists(path)):
        why = "the path is a symbolic link that leads nowhere (or in a loop)"
    elif exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        why += " (is it read-only?)"
    if done:
        return (f"cannot change the dataset at {str(path)!r}: {why}; done before that: {'; '.join(done)}; "
                f"`invphys dataset verify {path}` shows where it stands")
    return f"cannot change the dataset at {str(path)!r}: {why}; nothing was changed"


def _read_json(path: Path) -> Any:
    """A store's JSON file through the bounded reader (:mod:`invphys.core.safe_read`: a regular file of at
    most :data:`MAX_JSON_BYTES`, UTF-8, no key twice in one object), its refusals as :class:`DatasetError`."""
    from invphys.core.safe_read import load_user_json

    try:
        return load_user_json(path, what="dataset file", max_bytes=MAX_JSON_BYTES)
    except InvphysError as exc:
        raise DatasetError(str(exc)) from None


def _metadata_problem(meta: Any) -> str | None:
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
            "written_at": _utcnow()}


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
        return f"column types differ: {_short(exc)}"
    return None


def _problems_message(path: Path, problems: list[PartProblem]) -> str:
    shown = "; ".join(p.text() for p in problems[:3])
    more = f" and {len(problems) - 3} more" if len(problems) > 3 else ""
    return (f"dataset {str(path)!r} has {len(problems)} bad part(s): {shown}{more}. "
            f"`invphys dataset verify {path}` lists them; `--repair` quarantines them")


def _check_first_ok(first_ok: int | None) -> None:
    if first_ok is not None and (isinstance(first_ok, bool) or not isinstance(first_ok, int) or first_ok < 1):
        raise ValueError(f"first_ok must be a positive int or None, not {first_ok!r}")


def _too_few_message(path: Path, held: int, wanted: int) -> str:
    return f"dataset {str(path)!r} holds {held} ok rows, fewer than the {wanted} asked for"


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


# ----------------------------------------------------------------------------------------------
# Parquet schema and row conversion
# ----------------------------------------------------------------------------------------------
def table_schema(param_names: tuple[str, ...], feature_names: tuple[str, ...]) -> Any:
    """The Arrow schema of a store's rows."""
    import pyarrow as pa

    fields = [pa.field("key", pa.string(), nullable=False), pa.field("sample_index", pa.int64())]
    fields += [pa.field(f"theta_{n}", pa.float64()) for n in param_names]
    fields += [pa.field(f"p_{n}", pa.float64()) for n in param_names]
    fields += [pa.field(f"f_{n}", pa.float64()) for n in feature_names]
    fields += [pa.field("status", pa.string()), pa.field("failure", pa.string()),
               pa.field("wall_time_s", pa.float64()), pa.field("substeps", pa.int64())]
    fields += [pa.field(c, pa.string()) for c in ("simulator", "simulator_version", "preset", "backend",
                                                  "device")]
    fields.append(pa.field("created_at", pa.timestamp("ms", tz="UTC")))
    return pa.schema(fields)


def rows_to_table(rows: Sequence[Row], param_names: tuple[str, ...], feature_names: tuple[str, ...]) -> Any:
    """An Arrow table of ``rows`` (features are null in failed rows)."""
    import pyarrow as pa

    d, m = len(param_names), len(feature_names)
    theta = np.stack([np.asarray(r.theta, dtype=np.float64).reshape(d) for r in rows])
    params = np.stack([np.asarray(r.params, dtype=np.float64).reshape(d) for r in rows])
    columns: dict[str, Any] = {"key": [r.key for r in rows], "sample_index": [int(r.sample_index) for r in rows]}
    for j, n in enumerate(param_names):
        columns[f"theta_{n}"] = theta[:, j]
    for j, n in enumerate(param_names):
        columns[f"p_{n}"] = params[:, j]
    feats: list[np.ndarray | None] = []
    status: list[str] = []
    failure: list[str | None] = []
    for r in rows:
        res = check_features(r.result, m)
        feats.append(None if not res.ok or res.features is None else np.asarray(res.features).ravel())
        status.append("ok" if res.ok else "failed")
        failure.append(None if res.ok else (res.failure or "failed (no reason given)")[:MAX_REASON_CHARS])
    for j, n in enumerate(feature_names):
        columns[f"f_{n}"] = [None if f is None else float(f[j]) for f in feats]
    columns["status"] = status
    columns["failure"] = failure
    columns["wall_time_s"] = [float(r.result.stats.wall_time_s) for r in rows]
    columns["substeps"] = [int(r.result.stats.substeps) for r in rows]
    columns["simulator"] = [r.result.stats.simulator for r in rows]
    columns["simulator_version"] = [r.result.stats.simulator_version for r in rows]
    columns["preset"] = [r.result.stats.preset for r in rows]
    columns["backend"] = [r.result.stats.backend for r in rows]
    columns["device"] = [r.result.stats.device for r in rows]
    now = datetime.now(UTC)
    columns["created_at"] = [now] * len(rows)
    schema = table_schema(param_names, feature_names)
    return pa.table({name: columns[name] for name in schema.names}, schema=schema)

