"""A store's rows: one finished run (:class:`Row`), the Arrow schema and table they are written as, and the
arrays they are read back as (:class:`DatasetArrays`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from invphys.core.results import SimulationResult

#: row columns besides theta_*, p_* and f_* (in order)
META_COLUMNS: tuple[str, ...] = ("status", "failure", "wall_time_s", "substeps", "simulator",
                                 "simulator_version", "preset", "backend", "device", "created_at")
MAX_REASON_CHARS = 500


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
