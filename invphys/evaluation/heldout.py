"""Rows a bundle never trained on, picked by key, from the dataset stores of its simulator and preset.

A bundle keeps its training rows (``data/train.npz``); each row's key is the hash of its normalised
parameters and the store's run identity (:func:`~invphys.core.dataset.row_key`). The held-out rows are
every ok row of the candidate stores (by default the bundle's own dataset and the stores beside it)
that holds the same problem as the bundle's dataset (:func:`~invphys.core.dataset_union.incompatibility`:
same parameter space, features, simulator name, version, preset and config) and whose key is not a
training key. Rows that are not draws from the prior are left out, since calibration is defined against
the prior: the rows an adaptive design chose (the rounds of a store's ``_design.json``) and stores
sampled otherwise (``sampler: edge``). Without the stores,
the bundle's own test split is used (and said so).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError


@dataclass
class HeldOut:
    """Held-out rows sorted by key: ``theta`` (N, d) normalised, ``y`` (N, M), ``keys``, ``source`` per row."""

    theta: np.ndarray
    y: np.ndarray
    keys: np.ndarray
    source: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.keys)

    def take(self, idx: np.ndarray) -> HeldOut:
        return HeldOut(self.theta[idx], self.y[idx], self.keys[idx], self.source[idx], self.info)

    def split(self) -> np.ndarray:
        """(N,) 0 or 1 per row, from its key alone (so a row keeps its split whatever else is held)."""
        return np.array([int(k[-8:], 16) % 2 for k in self.keys], dtype=np.int64)


def _identity(meta: dict[str, Any]) -> Any:
    from invphys.core.dataset import RunIdentity

    ident = meta.get("identity") or {}
    return RunIdentity(**{k: str(ident.get(k, "")) for k in ("simulator", "preset", "backend", "version", "config")})


def _design_keys(path: Path, meta: dict[str, Any]) -> set[str]:
    """Keys of the rows an adaptive design chose in the store at ``path`` (none without a design)."""
    from invphys.core.dataset import row_keys

    plan = path / "_design.json"
    if not plan.is_file():
        return set()
    try:
        rounds = json.loads(plan.read_text())["rounds"]
        points = [p for r in rounds for p in r["points"]]
    except (ValueError, KeyError, TypeError):
        raise InvphysError(f"{plan} is unreadable: cannot tell its adaptive rows from its uniform ones") from None
    return set(row_keys(np.asarray(points, dtype=np.float64), _identity(meta))) if points else set()


def candidate_stores(bundle: Any, stores: Sequence[str | Path] | None) -> list[Path]:
    """The given stores, else the bundle's dataset (its manifest path) and the stores beside it."""
    if stores:
        return [Path(s) for s in stores]
    primary = Path(str(bundle.manifest.get("dataset", {}).get("path", "")))
    if not (primary / "_metadata.json").is_file():
        return []
    beside = sorted(p for p in primary.parent.iterdir() if p != primary and (p / "_metadata.json").is_file())
    return [primary, *beside]


def _simulator_name(bundle: Any) -> str:
    """The registered name of the bundle's simulator (its spec may name it by ``module:Class``)."""
    given = str(bundle.manifest["simulator"].get("name", ""))
    try:
        return str(getattr(bundle.registry.get("simulator", given), "name", given))
    except InvphysError:
        return given


#: samplers whose rows are draws from the prior (uniform on the normalised box); ``edge`` is not
PRIOR_SAMPLERS: frozenset[str] = frozenset({"uniform", "sobol", "lhs"})


def _matches_bundle(bundle: Any, meta: dict[str, Any]) -> str | None:
    """Why a store's rows are not the bundle's problem or not prior draws (None: they are both)."""
    sim = bundle.manifest["simulator"]
    ident = meta.get("identity") or {}
    preset = (sim.get("config") or {}).get("preset")
    name = _simulator_name(bundle)
    if ident.get("simulator") != name:
        return f"simulator {ident.get('simulator')!r}, the bundle's is {name!r}"
    if ident.get("version") != str(sim.get("version")):
        return f"simulator version {ident.get('version')!r}, the bundle's is {sim.get('version')!r}"
    if preset is not None and ident.get("preset") != preset:
        return f"preset {ident.get('preset')!r}, the bundle's is {preset!r}"
    if tuple(meta.get("feature_names") or ()) != tuple(bundle.feature_names):
        return "other features"
    if tuple(meta.get("param_names") or ()) != tuple(bundle.space.names):
        return "other parameters"
    sessions = meta.get("sessions")
    samplers = {str(x.get("sampler")) for x in sessions if isinstance(x, dict)} if isinstance(sessions, list) else set()
    other = sorted(samplers - PRIOR_SAMPLERS - {"None"})
    if other:
        return f"sampled with {', '.join(other)}, not from the prior (calibration is defined against the prior)"
    return None


def heldout_rows(bundle: Any, stores: Sequence[str | Path] | None = None) -> HeldOut:
    """The rows of ``stores`` (default :func:`candidate_stores`) the bundle never trained on."""
    from invphys.core.dataset import DatasetStore, row_keys
    from invphys.core.dataset_union import incompatibility

    paths = candidate_stores(bundle, stores)
    train_theta = bundle.data("train")[0]
    info: dict[str, Any] = {"stores": {}, "skipped": {}}
    ref: dict[str, Any] | None = None
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]] = []
    seen: set[str] = set()
    matched: set[str] = set()
    for path in paths:
        if not (path / "_metadata.json").is_file():
            raise InvphysError(f"no dataset store at {str(path)!r}")
        store = DatasetStore(path)
        meta = store.metadata
        why = _matches_bundle(bundle, meta) or (incompatibility(ref, meta) if ref is not None else None)
        if why:
            info["skipped"][str(path)] = why
            continue
        ref = ref or meta
        arr = store.arrays(ok_only=True)
        train_keys = set(row_keys(train_theta, _identity(meta)))
        adaptive = _design_keys(path, meta)
        keys = arr.keys.astype(str)
        in_train = np.array([k in train_keys for k in keys], dtype=bool)
        matched.update(keys[in_train].tolist())
        chosen = np.array([k in adaptive for k in keys], dtype=bool)
        fresh = np.array([k not in seen for k in keys], dtype=bool)
        keep = ~in_train & ~chosen & fresh & np.all(np.isfinite(arr.y), axis=1)
        seen.update(keys.tolist())
        info["stores"][str(path)] = {"ok_rows": len(keys), "training_rows": int(in_train.sum()),
                                     "adaptive_rows_left_out": int((chosen & ~in_train).sum()),
                                     "held_out": int(keep.sum())}
        parts.append((arr.theta[keep], arr.y[keep], keys[keep], str(path)))
    info["training_rows"] = len(train_theta)
    info["training_rows_found"] = len(matched)
    if not parts:
        return _test_split(bundle, info)
    theta = np.concatenate([p[0] for p in parts])
    y = np.concatenate([p[1] for p in parts])
    keys = np.concatenate([p[2] for p in parts])
    source = np.concatenate([np.full(len(p[2]), p[3], dtype=object) for p in parts])
    order = np.argsort(keys, kind="stable")
    info["rows"] = len(keys)
    return HeldOut(theta[order], y[order], keys[order], source[order], info)


def _test_split(bundle: Any, info: dict[str, Any]) -> HeldOut:
    """The bundle's own test split (``data/test.npz``), keyed like a store of its simulator."""
    from invphys.core.dataset import RunIdentity, row_keys

    theta, y = bundle.data("test")
    sim = bundle.manifest["simulator"]
    ident = RunIdentity(simulator=_simulator_name(bundle), preset=str((sim.get("config") or {}).get("preset", "")),
                        version=str(sim.get("version", "")))
    keys = np.array(row_keys(theta, ident), dtype=object)
    ok = np.all(np.isfinite(y), axis=1)
    order = np.argsort(keys[ok], kind="stable")
    info.update(rows=int(ok.sum()), note="no dataset store of the bundle found: its own test split (data/test.npz)")
    return HeldOut(theta[ok][order], y[ok][order], keys[ok][order],
                   np.full(int(ok.sum()), "data/test.npz", dtype=object), info)
