"""The real simulator in the loop: ask/tell CMA-ES per target, every target's population in one batch.

:class:`SimulatorEvaluator` turns normalised parameters into features by running the simulator (a
whole batch per call) and counts simulator runs against a budget. :func:`refine_targets` refines
many targets at once: each target has its own ask/tell search (CMA-ES in [0, 1]^d, started at a
given answer), and each generation of *all* targets is simulated as one batch, so on a GPU a
generation costs about one batched run. Each target's answer is the best simulated point (its start
included), so it has no reality gap by construction.

Each target's search is seeded from the caller's seed and the target's own values (:func:`target_seeds`) and
draws from a random state of its own (the ``cma`` package draws from NumPy's global one), so a target's
answer does not depend on its position, on the other targets or on the batch.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.objectives import recovery_reward


class SimulatorEvaluator:
    """Features (B, M) of normalised parameters (B, d) from the real simulator; failed runs are NaN rows.

    ``simulate_features(theta) -> (features, failures, stats)`` does the work (e.g. the simulator
    validator's ``simulate_features`` bound to a simulator and extractor). ``budget`` caps the runs
    in all (None: unlimited); a call that would exceed it raises :class:`InvphysError`.
    """

    def __init__(self, simulate_features: Callable[[np.ndarray], Any], budget: int | None = None) -> None:
        self._simulate = simulate_features
        self.budget = budget
        self.runs = 0
        self.batches = 0
        self.failed = 0
        self.wall_time_s = 0.0
        self.device = ""

    @classmethod
    def from_validator(cls, validator: Any, simulator: Any, extractor: Any, budget: int | None = None
                       ) -> SimulatorEvaluator:
        """Run through a validator with ``simulate_features`` (the ``simulator`` validator)."""
        return cls(lambda theta: validator.simulate_features(theta, simulator, extractor), budget)

    @property
    def remaining(self) -> int | None:
        return None if self.budget is None else self.budget - self.runs

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        if self.budget is not None and self.runs + len(theta) > self.budget:
            raise InvphysError(f"simulator budget exhausted: {self.runs} of {self.budget} runs spent, "
                               f"{len(theta)} more asked")
        t0 = time.perf_counter()
        sim = self._simulate(np.clip(theta, 0.0, 1.0))
        # the runs' own times when every run has stats: memoised runs (a resumed validation) keep their cost
        own = [s.wall_time_s for s in sim.stats if s is not None]
        self.wall_time_s += float(sum(own)) if own and len(own) == len(sim.stats) else time.perf_counter() - t0
        self.runs += len(theta)
        self.batches += 1
        self.failed += sum(1 for f in sim.failures if f)
        devices = {s.device for s in sim.stats if s is not None and s.device}
        if devices:
            self.device = ",".join(sorted(devices))
        return np.asarray(sim.features, dtype=np.float64)


@dataclass
class Refined:
    """One target's refinement: best ``theta``, its ``score`` and ``features``, points ``evaluated``."""

    theta: np.ndarray
    score: float
    features: np.ndarray | None
    evaluated: int
    history: list[tuple[int, float]] = field(default_factory=list)
    #: with ``keep=True``: every simulated point (n, d), its score (n,) and features (n, M), the start first
    points: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def row_seed(seed: int, row: np.ndarray, stream: str = "", copy: int = 0) -> int:
    """A 32-bit seed from ``seed``, a ``stream`` name and the float64 values of ``row`` (NaN: missing,
    -0.0 as 0.0); ``copy`` tells apart the copies of one row that ask for independent draws."""
    row = np.asarray(row, dtype=np.float64).reshape(-1)
    given = np.isfinite(row)
    h = hashlib.sha256(b"invphys-row-seed-1\0")
    h.update(int(seed).to_bytes(8, "little", signed=False) + int(copy).to_bytes(4, "little"))
    h.update(stream.encode() + b"\0")
    h.update(np.ascontiguousarray(np.where(given, row, 0.0) + 0.0, dtype="<f8").tobytes())
    h.update(np.packbits(given).tobytes() + len(row).to_bytes(4, "little"))
    return int.from_bytes(h.digest()[:4], "little")


def target_seeds(seed: int, targets: np.ndarray, stream: str = "refine") -> list[int]:
    """One seed per row of ``targets`` (T, M) from (``seed``, the row's values): the k-th copy of a row
    (counted in order among equal rows) gets copy ``k``, so repeated targets get independent searches."""
    seen: dict[bytes, int] = {}
    out = []
    for row in np.atleast_2d(np.asarray(targets, dtype=np.float64)):
        key = (np.where(np.isfinite(row), row, np.inf) + 0.0).tobytes()
        out.append(row_seed(seed, row, stream, seen.get(key, 0)))
        seen[key] = seen.get(key, 0) + 1
    return out


class OwnRandom:
    """A NumPy global random state of one's own (``cma`` draws from the global one): inside
    :meth:`use`, ``np.random`` is this state; the caller's is restored after."""

    def __init__(self, seed: int) -> None:
        self._state: Any = np.random.RandomState(int(seed) % 2**32).get_state()

    @contextmanager
    def use(self) -> Iterator[None]:
        outer = np.random.get_state()
        np.random.set_state(self._state)
        try:
            yield
        finally:
            self._state = np.random.get_state()
            np.random.set_state(outer)


def refine_targets(targets: np.ndarray, starts: np.ndarray, scales: np.ndarray,
                   evaluate: Callable[[np.ndarray], np.ndarray], budget: int, popsize: int = 8,
                   sigma0: float = 0.1, seed: int = 0, kappa: float = 3.0,
                   score: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                   keep: bool = False, seeds: Sequence[int] | None = None) -> list[Refined]:
    """Refine each target's start with ask/tell CMA-ES; one ``evaluate`` call per generation for all.

    Args:
        targets: (T, M) target features; starts: (T, d) normalised start points.
        evaluate: features (B, M) of normalised parameters (B, d); NaN rows for failures (score -inf).
        budget: evaluations per target, the start's included.
        score: ``score(features (B, M), targets (B, M)) -> (B,)``; default R_gt with ``kappa``.
        keep: fill each target's :attr:`Refined.points` (every point it simulated, in order).
        seeds: one seed per target (default :func:`target_seeds` of ``seed`` and ``targets``); each
            search draws from a random state of its own, so no answer depends on the other targets.
    """
    from invphys.core.spaces import raw_space
    from invphys.plugins.optimizers.cma_es import CMAES

    targets = np.atleast_2d(np.asarray(targets, dtype=np.float64))
    starts = np.clip(np.atleast_2d(np.asarray(starts, dtype=np.float64)), 0.0, 1.0)
    if len(targets) != len(starts):
        raise InvphysError(f"refine: {len(targets)} targets and {len(starts)} starts")
    if budget < 1:
        raise InvphysError(f"refine: the budget per target must be >= 1, got {budget}")
    score = score or (lambda y, t: recovery_reward(y, t, scales, kappa))

    def scored(y: np.ndarray, t: np.ndarray) -> np.ndarray:
        s = np.asarray(score(y, t), dtype=np.float64)
        return np.where(np.all(np.isfinite(y), axis=1) & np.isfinite(s), s, -np.inf)

    n_t, d = starts.shape
    space = raw_space(d)
    cma = CMAES(popsize=popsize, sigma0=sigma0, budget=max(budget - 1, 1), restarts=True)
    seeds = target_seeds(seed, targets) if seeds is None else [int(s) for s in seeds]
    if len(seeds) != n_t:
        raise InvphysError(f"refine: {n_t} targets and {len(seeds)} seeds")
    randoms = [OwnRandom(s) for s in seeds]
    searches = []
    for t in range(n_t):
        with randoms[t].use():
            searches.append(cma.ask_tell(space, seeds[t], starts[t], max(budget - 1, 1)))
    y0 = evaluate(starts)
    s0 = scored(y0, targets)
    out = [Refined(starts[t].copy(), float(s0[t]), y0[t].copy(), 1, [(1, float(s0[t]))]) for t in range(n_t)]
    kept: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [
        [(starts[t:t + 1], s0[t:t + 1], np.atleast_2d(y0[t]))] for t in range(n_t)]
    while True:
        asks = []
        for t, search in enumerate(searches):
            left = budget - out[t].evaluated
            with randoms[t].use():
                pts = search.ask() if left > 0 and not search.done else np.empty((0, d))
            asks.append(pts[:left])
        sizes = [len(a) for a in asks]
        if sum(sizes) == 0:
            break
        theta = np.concatenate([a for a in asks if len(a)])
        y = evaluate(theta)
        owners = np.repeat(np.arange(n_t), sizes)
        s = scored(y, targets[owners])
        start = 0
        for t, n in enumerate(sizes):
            if n == 0:
                continue
            sl = slice(start, start + n)
            start += n
            with randoms[t].use():
                searches[t].tell(asks[t], s[sl])
            if keep:
                kept[t].append((np.array(asks[t]), s[sl].copy(), y[sl].copy()))
            out[t].evaluated += n
            i = int(np.argmax(s[sl]))
            if s[sl][i] > out[t].score:
                out[t].theta, out[t].score, out[t].features = asks[t][i].copy(), float(s[sl][i]), y[sl][i].copy()
            out[t].history.append((out[t].evaluated, out[t].score))
    if keep:
        for t in range(n_t):
            out[t].points = tuple(np.concatenate([k[j] for k in kept[t]]) for j in range(3))  # type: ignore[assignment]
    return out
