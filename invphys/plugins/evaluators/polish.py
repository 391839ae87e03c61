"""Simulator-in-the-loop polish of answers that were already simulated (``active.polish``).

:func:`polish` runs :func:`~invphys.plugins.evaluators.simulator_loop.refine_targets` (ask/tell
CMA-ES on the real simulator, each generation of all targets in one batch) from each target's best
simulated answer, only for targets whose R_actual is below a threshold. The starts' features are
known, so they are not simulated again; a target's answer is the best simulated point, its start
included, so no target gets worse.

:class:`BatchLog` makes it resumable: every simulated batch (points, features, seconds, device) is
appended atomically to an ``.npz`` file; a re-run with the same seeds asks the same points and gets
their features from the log instead of the simulator, so a stopped polish loses at most the batch in
flight, a finished one costs nothing again, and the logged runs still count in the cost.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


class BatchLog:
    """Memoised batches of a deterministic search: replay the logged ones, simulate and log the rest.

    ``evaluator`` is a :class:`~invphys.plugins.evaluators.simulator_loop.SimulatorEvaluator` (or
    anything with ``__call__``, ``wall_time_s`` and ``device``). Batch ``i`` of a run is replayed when
    the logged batch ``i`` has the same points (within ``atol``); the first mismatch drops the rest of
    the log (the search diverged) and simulates from there. ``key`` names what the log was made for:
    another key starts an empty log. ``chunk``: a call with more points is simulated and logged in
    chunks of that many (a stop loses at most one chunk). ``on_batch(runs, replayed)`` is called after
    each batch (progress bars).
    """

    def __init__(self, path: Path | None, key: str, evaluator: Any,
                 log: Callable[[str], None] | None = None, atol: float = 1e-9, chunk: int | None = None,
                 on_batch: Callable[[int, bool], None] | None = None) -> None:
        self.path, self.key, self.evaluator, self.atol, self.chunk = path, key, evaluator, atol, chunk
        self._log = log or (lambda _msg: None)
        self._on_batch = on_batch or (lambda _runs, _replayed: None)
        self.batches: list[dict[str, Any]] = self._load()
        self.calls = 0
        self.runs = 0
        self.replayed_runs = 0
        self.seconds = 0.0
        self.device = ""

    def _load(self) -> list[dict[str, Any]]:
        if self.path is None or not Path(self.path).is_file():
            return []
        try:
            with np.load(self.path) as z:
                if str(z["key"]) != self.key:
                    self._log(f"{Path(self.path).name} was made for other settings; polishing afresh")
                    return []
                meta = json.loads(str(z["meta"]))
                cuts = np.cumsum([m["runs"] for m in meta])[:-1]
                thetas, ys = np.split(z["theta"], cuts), np.split(z["y"], cuts)
        except (OSError, ValueError, KeyError) as exc:
            self._log(f"{Path(self.path).name} is unreadable ({exc}); polishing afresh")
            return []
        return [{**m, "theta": t, "y": y} for m, t, y in zip(meta, thetas, ys, strict=True)]

    def _save(self) -> None:
        if self.path is None:
            return
        from invphys.core.atomic import atomic_write_bytes

        meta = [{k: b[k] for k in ("runs", "seconds", "device")} for b in self.batches]
        buf = io.BytesIO()
        np.savez_compressed(buf, key=np.array(self.key), meta=np.array(json.dumps(meta)),
                            theta=np.concatenate([b["theta"] for b in self.batches]),
                            y=np.concatenate([b["y"] for b in self.batches]))
        atomic_write_bytes(Path(self.path), buf.getvalue())

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        step = self.chunk or len(theta) or 1
        return np.concatenate([self._batch(theta[a:a + step]) for a in range(0, max(len(theta), 1), step)])

    def _batch(self, theta: np.ndarray) -> np.ndarray:
        i = self.calls
        self.calls += 1
        if i < len(self.batches):
            b = self.batches[i]
            if b["theta"].shape == theta.shape and np.allclose(b["theta"], theta, rtol=0.0, atol=self.atol):
                self.runs += len(theta)
                self.replayed_runs += len(theta)
                self.seconds += float(b["seconds"])
                self.device = b["device"] or self.device
                self._log(f"polish batch {i}: {len(theta)} runs replayed from {Path(str(self.path)).name}")
                self._on_batch(len(theta), True)
                return np.array(b["y"], dtype=np.float64)
            self._log(f"polish batch {i}: the search asked other points than logged; simulating from here")
            del self.batches[i:]
        s0 = self.evaluator.wall_time_s
        y = np.asarray(self.evaluator(theta), dtype=np.float64)
        seconds = float(self.evaluator.wall_time_s - s0)
        self.runs += len(theta)
        self.seconds += seconds
        self.device = getattr(self.evaluator, "device", "") or self.device
        self.batches.append({"runs": len(theta), "seconds": seconds, "device": self.device,
                             "theta": theta.copy(), "y": y.copy()})
        self._save()
        self._log(f"polish batch {i}: {len(theta)} runs simulated in {seconds:.1f} s")
        self._on_batch(len(theta), False)
        return y


@dataclass
class Polished:
    """The polish's outcome for all targets (unpolished ones unchanged, 0 runs)."""

    theta: np.ndarray
    r_actual: np.ndarray
    features: np.ndarray
    runs: np.ndarray  # new simulator runs per target
    polished: np.ndarray  # bool mask
    seconds: float  # simulator seconds in all (replayed batches included)
    batches: int
    replayed_runs: int
    device: str


def polish(targets: np.ndarray, theta: np.ndarray, r_actual: np.ndarray, features: np.ndarray,
           scales: np.ndarray, evaluate: Any, budget: int, popsize: int = 8, sigma0: float = 0.05,
           below: float = 0.95, seed: int = 0,
           score: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None) -> Polished:
    """CMA-ES on the simulator from each answer with ``r_actual < below`` (``budget`` new runs each).

    ``evaluate``: a :class:`BatchLog` or a ``SimulatorEvaluator`` (features of normalised points,
    NaN rows for failures). A start whose ``features`` are not finite is simulated first (1 run).
    ``score(features (B, M), targets (B, M)) -> (B,)`` scores points and must match how ``r_actual``
    was computed (default: R_gt with kappa 3 over every feature; the inverter passes a masked R).
    """
    from invphys.plugins.evaluators.simulator_loop import refine_targets

    theta, r_actual = np.array(theta, dtype=np.float64), np.array(r_actual, dtype=np.float64)
    features = np.array(features, dtype=np.float64)
    n = len(theta)
    mask = ~(r_actual >= below)  # NaN / -inf (never simulated successfully) are polished too
    idx = np.flatnonzero(mask)
    runs = np.zeros(n, dtype=np.int64)
    seconds0 = float(getattr(evaluate, "seconds", getattr(evaluate, "wall_time_s", 0.0)))
    if len(idx) == 0:
        return Polished(theta, r_actual, features, runs, mask, 0.0, 0, 0, "")
    known = features[idx]
    resim = ~np.all(np.isfinite(known), axis=1)
    calls = [0]

    def ev(points: np.ndarray) -> np.ndarray:
        calls[0] += 1
        if calls[0] > 1:
            return evaluate(points)
        out = known.copy()  # the starts: already simulated (their features are the answers' features)
        if resim.any():
            out[resim] = evaluate(points[resim])
        return out

    targets = np.asarray(targets, dtype=np.float64)
    refined = refine_targets(targets[idx], theta[idx], scales, ev, budget + 1, popsize, sigma0, seed=seed, score=score)
    for j, (i, x) in enumerate(zip(idx, refined, strict=True)):
        runs[i] = x.evaluated - 1 + int(resim[j])
        if x.features is None or not np.all(np.isfinite(x.features)):
            continue
        r_new = x.score  # refine_targets scored it with ``score`` (default: the same R_gt as r_actual)
        if r_new > r_actual[i] or not np.isfinite(r_actual[i]):
            theta[i], r_actual[i], features[i] = x.theta, r_new, x.features
    seconds = float(getattr(evaluate, "seconds", getattr(evaluate, "wall_time_s", 0.0))) - seconds0
    return Polished(theta, r_actual, features, runs, mask, seconds, calls[0] - 1 + int(resim.any()),
                    int(getattr(evaluate, "replayed_runs", 0)), str(getattr(evaluate, "device", "") or ""))
