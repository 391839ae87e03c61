"""Crash-safe memo of simulated parameter vectors for the validate stage (resumable validation).

Every simulated vector is appended to a JSON-lines file as its batch finishes (written, flushed and
fsynced): its key, features (None for a failed run), failure reason and run stats. A re-run, or a run
killed and started again, reads the file, simulates only the vectors it lacks and gets the finished
ones back bit for bit (JSON keeps float64 exactly). A torn last line (a kill mid-write) is cut off on
load. Keys hash the rounded vector together with an ``identity`` (simulator, features and validator
settings), so a changed simulator never reuses old runs. Records written under an earlier form of the
same identity (``legacy``) are still found; new records use ``identity``.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.results import RunStats


class SimCheckpoint:
    """Append-only memo ``key -> (features, failure, stats)`` backed by ``path`` (JSON lines)."""

    def __init__(self, path: Path, identity: str, legacy: Collection[str] = ()) -> None:
        self.path = Path(path)
        self.identity = identity
        self.legacy = tuple(x for x in legacy if x != identity)
        self.done: dict[str, dict[str, Any]] = {}
        self.reused = 0
        self.simulated = 0
        self._load()

    def _load(self) -> None:
        if not self.path.is_file():
            return
        raw = self.path.read_bytes()
        good = 0
        for line in raw.splitlines(keepends=True):
            if not line.endswith(b"\n"):
                break  # torn last line
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                break
            self.done[rec["key"]] = rec
            good += len(line)
        if good < len(raw):
            with open(self.path, "r+b") as fh:
                fh.truncate(good)
                fh.flush()
                os.fsync(fh.fileno())

    def key(self, theta: np.ndarray, identity: str | None = None) -> str:
        blob = (identity or self.identity).encode() + np.round(np.asarray(theta, dtype=np.float64), 12).tobytes()
        return hashlib.sha256(blob).hexdigest()[:24]

    def _find(self, theta: np.ndarray) -> str:
        """The key under which ``theta`` is memoised (a legacy identity's if only that one has it), else
        its key under the current identity."""
        key = self.key(theta)
        if key not in self.done:
            for old in self.legacy:
                k = self.key(theta, old)
                if k in self.done:
                    return k
        return key

    def append(self, records: list[dict[str, Any]]) -> None:
        """Append ``records`` durably (one fsync per batch)."""
        if not records:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "ab") as fh:
            fh.write(b"".join(json.dumps(r, separators=(",", ":")).encode() + b"\n" for r in records))
            fh.flush()
            os.fsync(fh.fileno())
        for r in records:
            self.done[r["key"]] = r

    @staticmethod
    def _record(key: str, theta: np.ndarray, features: Any, failure: str | None, stats: Any) -> dict[str, Any]:
        return {"key": key, "theta": np.asarray(theta).tolist(),
                "features": None if features is None else np.asarray(features).tolist(), "failure": failure,
                "stats": None if stats is None else stats.to_dict()}

    def simulate(self, theta: np.ndarray, simulate: Callable[..., Any], batch_size: int, n_features: int,
                 keep_trajectories: bool | Collection[int] = False, on_run: Callable[[int], None] | None = None
                 ) -> Any:
        """Like ``simulate(theta, keep_trajectories=..., on_run=..., on_record=...)`` (a validator's
        ``simulate_features`` bound to simulator and extractor), simulating only rows not in the memo,
        ``batch_size`` at a time. Each run is appended as its ``on_record`` reports it (as it finishes), and
        whatever a batch did not report when the batch returns, so a killed call loses no finished run.
        Returns a ``SimulatedFeatures`` for all rows; trajectories exist only for rows simulated in this call."""
        from invphys.plugins.validators.simulator import SimulatedFeatures

        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        keys = [self._find(t) for t in theta]
        first = {k: i for i, k in reversed(list(enumerate(keys)))}
        todo = sorted(i for k, i in first.items() if k not in self.done)
        trajs: list[Any] = [None] * len(theta)
        self.reused += len(first) - len(todo)
        for start in range(0, len(todo), max(1, batch_size)):
            rows = todo[start:start + max(1, batch_size)]
            keep: bool | set[int] = keep_trajectories is True or {
                j for j, r in enumerate(rows) if keep_trajectories and r in keep_trajectories}
            stored: set[int] = set()

            def store(j: int, features: Any, failure: str | None, stats: Any, rows: list[int] = rows,
                      stored: set[int] = stored) -> None:
                self.append([self._record(keys[rows[j]], theta[rows[j]], features, failure, stats)])
                stored.add(j)

            sim = simulate(theta[rows], keep_trajectories=keep, on_record=store,
                           on_run=None if on_run is None else (lambda j, rows=rows: on_run(rows[j])))
            self.append([self._record(keys[r], theta[r], sim.features[j] if sim.failures[j] is None else None,
                                      sim.failures[j], sim.stats[j])
                         for j, r in enumerate(rows) if j not in stored])
            for j, r in enumerate(rows):
                trajs[r] = sim.trajectories[j]
            self.simulated += len(rows)
        m = n_features
        feats, failures, stats = [], [], []
        for k in keys:
            rec = self.done[k]
            feats.append(rec["features"])
            failures.append(rec["failure"])
            stats.append(None if rec["stats"] is None else RunStats(**rec["stats"]))
        out = np.array([f if f is not None else [np.nan] * m for f in feats], dtype=np.float64).reshape(len(keys), m)
        return SimulatedFeatures(out, failures, stats, trajs)
