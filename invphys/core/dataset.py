"""The dataset store: append-only, crash-safe Parquet parts plus a JSON metadata file.

A store is a directory::

    DIR/_metadata.json                 provenance, parameter space, feature names, sessions, totals
    DIR/part-000000-1a2b3c4d.parquet   one part per flushed batch of rows (never rewritten)
    DIR/part-000001-....parquet
    DIR/.lock                          held (flock) by the one process appending

``pandas.read_parquet(DIR)`` reads every row (files starting with ``.`` or ``_`` are skipped by
pyarrow, which is why the metadata file is ``_metadata.json``). Each part is written under a temporary
name, fsynced and renamed atomically, so a reader never sees half a part and a killed writer loses
only the rows it had not flushed. Every row carries a key: a stable hash of its normalised parameters
(rounded to :data:`KEY_DECIMALS` decimals), the simulator's name, preset, backend and version. A re-run
skips the keys already present, so it resumes instead of duplicating.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.atomic import atomic_write_bytes, write_json
from invphys.core.errors import InvphysError
from invphys.core.results import SimulationResult

FORMAT = "invphys-dataset/1"
METADATA_FILE = "_metadata.json"
LOCK_FILE = ".lock"
KEY_DECIMALS = 10
#: row columns besides theta_*, p_* and f_* (in order)
META_COLUMNS: tuple[str, ...] = ("status", "failure", "wall_time_s", "substeps", "simulator",
                                 "simulator_version", "preset", "backend", "device", "created_at")
MAX_REASON_CHARS = 500


class DatasetError(InvphysError):
    """A dataset path is missing, unreadable, locked, or incompatible with the requested simulator."""


@dataclass(frozen=True)
class RunIdentity:
    """What, besides the parameters, makes two simulation runs the same run (part of each row key)."""

    simulator: str
    preset: str = ""
    backend: str = ""
    version: str = ""

    @classmethod
    def of(cls, simulator: Any) -> RunIdentity:
        """The identity of a :class:`~invphys.core.interfaces.Simulator` instance (its configured
        ``preset`` and ``backend`` fields when its Config has them)."""
        cfg = getattr(simulator, "config", None)
        return cls(simulator=str(simulator.name), preset=str(getattr(cfg, "preset", "") or ""),
                   backend=str(getattr(cfg, "backend", "") or ""), version=str(simulator.version))

    def to_dict(self) -> dict[str, str]:
        return {"simulator": self.simulator, "preset": self.preset, "backend": self.backend,
                "version": self.version}


def round_theta(theta: np.ndarray) -> np.ndarray:
    """Normalised parameters rounded to the key precision (what the store keeps and keys)."""
    return np.round(np.clip(np.asarray(theta, dtype=np.float64), 0.0, 1.0), KEY_DECIMALS) + 0.0


def row_key(theta_row: Sequence[float] | np.ndarray, identity: RunIdentity) -> str:
    """The stable key of one run: sha256 over fixed-precision text, first 24 hex digits.

    Text (not float bits) makes it identical across processes, machines and NumPy versions.
    """
    values = ",".join(f"{v:.{KEY_DECIMALS}f}" for v in round_theta(np.asarray(theta_row)).ravel())
    text = f"{identity.simulator}|{identity.preset}|{identity.backend}|{identity.version}|{values}"
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


class DatasetStore:
    """An append-only store of simulation rows in ``path`` (see the module docstring)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._lock_fd: int | None = None

    def __repr__(self) -> str:
        return f"DatasetStore({str(self.path)!r})"

    # -- metadata ------------------------------------------------------------------------------
    @property
    def metadata_path(self) -> Path:
        return self.path / METADATA_FILE

    @property
    def exists(self) -> bool:
        return self.metadata_path.is_file()

    @property
    def metadata(self) -> dict[str, Any]:
        """The parsed ``_metadata.json`` (raises :class:`DatasetError` when there is no store)."""
        if not self.exists:
            hint = " (it has Parquet files but no _metadata.json)" if self.parts() else ""
            raise DatasetError(f"no invphys dataset at {str(self.path)!r}{hint}")
        try:
            return json.loads(self.metadata_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise DatasetError(f"cannot read {self.metadata_path}: {exc}") from exc

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

    # -- writing -------------------------------------------------------------------------------
    def create_or_check(self, metadata: dict[str, Any]) -> dict[str, Any]:
        """Create the store with ``metadata``, or check that an existing store is compatible.

        ``metadata`` must hold ``identity``, ``param_names`` and ``feature_names``; an existing store
        whose values differ raises :class:`DatasetError` (one store holds one kind of run).
        Returns the store's metadata.
        """
        if not self.exists:
            if self.path.exists() and any(p for p in self.path.iterdir() if not p.name.startswith(".")):
                raise DatasetError(f"{str(self.path)!r} exists and is not an invphys dataset; "
                                   "choose an empty or new directory")
            meta = {"format": FORMAT, "created_at": _utcnow(), "key_decimals": KEY_DECIMALS,
                    "sessions": [], **metadata}
            self.write_metadata(meta)
            return meta
        meta = self.metadata
        for field_name in ("identity", "param_names", "feature_names"):
            have, want = meta.get(field_name), metadata.get(field_name)
            if have != want:
                raise DatasetError(
                    f"the dataset at {str(self.path)!r} holds runs with {field_name} = {have}, "
                    f"but this generation has {field_name} = {want}; write to another directory"
                )
        return meta

    @contextlib.contextmanager
    def writer(self) -> Iterator[DatasetStore]:
        """Hold the store's write lock (one appending process at a time) and clear stale temp files."""
        import fcntl

        self.path.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise DatasetError(f"another process is writing to {str(self.path)!r}") from None
        self._lock_fd = fd
        try:
            for tmp in [*self.path.glob(".part-*.tmp"), *self.path.glob(f".{METADATA_FILE}.*.tmp")]:
                tmp.unlink(missing_ok=True)  # left by a killed writer; never visible to readers
            yield self
        finally:
            self._lock_fd = None
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def append(self, rows: Sequence[Row]) -> Path | None:
        """Write ``rows`` as one new Parquet part (atomically); returns its path (None if empty)."""
        if not rows:
            return None
        import pyarrow as pa
        import pyarrow.parquet as pq

        meta = self.metadata
        table = rows_to_table(rows, tuple(meta["param_names"]), tuple(meta["feature_names"]))
        seq = len(self.parts())
        name = f"part-{seq:06d}-{uuid.uuid4().hex[:8]}.parquet"
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink, compression="zstd")
        atomic_write_bytes(self.path / name, sink.getvalue().to_pybytes(), tmp_name=f".{name}.tmp")
        return self.path / name

    # -- reading -------------------------------------------------------------------------------
    def parts(self) -> list[Path]:
        """The committed Parquet parts, in write order."""
        if not self.path.is_dir():
            return []
        return sorted(p for p in self.path.glob("part-*.parquet") if p.is_file())

    def keys(self) -> set[str]:
        """Keys of every stored row (ok and failed)."""
        import pyarrow.parquet as pq

        out: set[str] = set()
        for part in self.parts():
            out.update(pq.read_table(part, columns=["key"]).column("key").to_pylist())
        return out

    def frame(self, ok_only: bool = False) -> Any:
        """All rows as a pandas DataFrame sorted by key (a key stored twice appears once)."""
        import pandas as pd
        import pyarrow as pa
        import pyarrow.parquet as pq

        meta = self.metadata
        schema = table_schema(tuple(meta["param_names"]), tuple(meta["feature_names"]))
        parts = self.parts()
        if parts:
            table = pa.concat_tables([pq.read_table(p).select(schema.names).cast(schema) for p in parts])
        else:
            table = schema.empty_table()
        df: pd.DataFrame = table.to_pandas()
        df = df.drop_duplicates("key", keep="first").sort_values("key", kind="stable").reset_index(drop=True)
        if ok_only:
            df = df[df["status"] == "ok"].reset_index(drop=True)
        return df

    def arrays(self, ok_only: bool = True) -> DatasetArrays:
        """The rows as :class:`DatasetArrays` (only successful runs unless ``ok_only=False``)."""
        meta = self.metadata
        pnames, fnames = tuple(meta["param_names"]), tuple(meta["feature_names"])
        df = self.frame(ok_only=ok_only)
        keys = df["key"].to_numpy(dtype=object)

        def block(prefix: str, names: tuple[str, ...]) -> np.ndarray:
            cols = [f"{prefix}{n}" for n in names]
            return df[cols].to_numpy(dtype=np.float64, na_value=np.nan).reshape(len(df), len(cols))

        return DatasetArrays(theta=block("theta_", pnames), y=block("f_", fnames), params=block("p_", pnames),
                             param_names=pnames, feature_names=fnames, keys=keys,
                             fingerprint=keys_fingerprint(list(keys)),
                             ok=(df["status"] == "ok").to_numpy(dtype=bool))

    def info(self) -> dict[str, Any]:
        """A JSON-ready summary: counts, failures by reason, provenance, feature percentiles."""
        meta = self.metadata
        df = self.frame()
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
            "parts": len(self.parts()),
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
        }


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

