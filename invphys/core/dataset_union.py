"""Training on several stores: a primary store plus extra stores whose rows join the training split only.

The primary store fixes the held-out split and the targets (its rows, its seed, its ``test_fraction``);
each extra store (``dataset.extra_train`` in a spec) adds its successful rows to the training rows (or,
for an entry ``{path, rows: N}``, its first N ok rows in store order), so a model trained on more data is
compared with the same held-out rows. Stores are joined only when they
hold the same problem: the same parameter space, parameter and feature names, and the same simulator
name, version and preset (and the same config hash where both stores record one). A row already in
the primary store (same key: same parameters, same simulator identity) is not added twice.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.dataset import DatasetArrays, DatasetError, DatasetStore

#: identity fields that must agree between joined stores (the backend may differ: same physics)
SAME_IDENTITY: tuple[str, ...] = ("simulator", "version", "preset")


def incompatibility(primary: dict[str, Any], extra: dict[str, Any]) -> str | None:
    """Why a store with metadata ``extra`` cannot join one with metadata ``primary`` (None: it can)."""
    for key in ("param_names", "feature_names", "parameter_space"):
        if primary.get(key) != extra.get(key):
            return f"its {key.replace('_', ' ')} differ"
    a, b = primary.get("identity") or {}, extra.get("identity") or {}
    for key in SAME_IDENTITY:
        if a.get(key) != b.get(key):
            return f"it was made by {key} {b.get(key)!r}, the primary store by {a.get(key)!r}"
    if a.get("config") and b.get("config") and a["config"] != b["config"]:
        return f"its simulator config hash {b['config']} differs from the primary store's {a['config']}"
    return None


def check_extra_stores(primary: Path, extras: Sequence[str | Path]) -> None:
    """Raise :class:`DatasetError` (one line) when an extra store is missing, unreadable or foreign."""
    meta = DatasetStore(primary).metadata
    seen = {Path(primary).resolve()}
    for extra in extras:
        path = Path(extra)
        if not (path / "_metadata.json").is_file():
            raise DatasetError(f"dataset.extra_train: no dataset at {str(path)!r}")
        if path.resolve() in seen:
            raise DatasetError(f"dataset.extra_train: {str(path)!r} is listed twice (or is the primary store)")
        seen.add(path.resolve())
        why = incompatibility(meta, DatasetStore(path).metadata)
        if why:
            raise DatasetError(f"dataset.extra_train: {str(path)!r} cannot join {str(primary)!r}: {why}")


def join_for_training(primary: DatasetArrays, extras: Sequence[DatasetArrays]) -> DatasetArrays:
    """``primary``'s rows first (in their order), then each extra's rows not already in ``primary``.

    The fingerprint hashes the parts' fingerprints, so a model records exactly which rows it saw.
    """
    known = set(primary.keys.tolist())
    parts = [primary]
    for extra in extras:
        keep = np.array([k not in known for k in extra.keys.tolist()], dtype=bool)
        known.update(extra.keys[keep].tolist())
        parts.append(_rows(extra, keep))
    if len(parts) == 1:
        return primary
    digest = hashlib.sha256("|".join(p.fingerprint for p in parts).encode()).hexdigest()[:16]
    return DatasetArrays(
        theta=np.concatenate([p.theta for p in parts]), y=np.concatenate([p.y for p in parts]),
        params=np.concatenate([p.params for p in parts]), param_names=primary.param_names,
        feature_names=primary.feature_names, keys=np.concatenate([p.keys for p in parts]),
        fingerprint=f"joined-{digest}", ok=np.concatenate([p.ok for p in parts]))


def _rows(a: DatasetArrays, keep: np.ndarray) -> DatasetArrays:
    return DatasetArrays(theta=a.theta[keep], y=a.y[keep], params=a.params[keep], param_names=a.param_names,
                         feature_names=a.feature_names, keys=a.keys[keep], fingerprint=a.fingerprint,
                         ok=a.ok[keep] if len(a.ok) else a.ok)
