"""Refine answers on the simulator at dataset speed (``invphys invert ... --sim-refine N``).

From each result's best candidates (its top-k, the amortised answer first), a per-target search on the
real simulator: the candidates not simulated yet are simulated, then a search from the best of them
(:func:`~invphys.evaluators.stream_refine.stream_refine`), ``budget`` runs per target in all. Strategies:
``cma`` (ask/tell CMA-ES) and ``corrected`` (the surrogate corrected by the target's own runs, searched
in a trust region: :mod:`~invphys.evaluators.corrected_refine`). ``known_starts`` adds the bundle's
stored training rows whose real features fit the target best as starts that cost no run (they were
simulated by the very simulator config the bundle was trained for: by construction, since they are the
bundle's own rows, unless ``overrides`` change the physics, when ``known_starts=0`` is the right call;
default: 8 for ``corrected``, the default strategy, 0 for ``cma``). A target stops asking for runs once its
best simulated R_actual reaches ``stop`` (default :data:`REFINE_STOP`, near the noise floor: re-simulating
the true parameters of fresh paper targets gives 0.993-0.996), decided from its own runs alone, so its runs are
the first runs of the same refine without a stop. With ``patience`` P (runs; default 0: off) a target also
stops once it stalls: its best simulated R_actual gained less than ``min_gain`` over its last P told runs
(checked before each generation once it has told P runs; starts known at no run count as before its first
run), again from its own runs alone. An answer whose simulated R_actual stays
below 0.5 gets a warning. Every target's runs share one open stream, so a target's next generation starts
while other targets' runs are still in flight. The answer is the best simulated point, so never worse than the
best simulated start; the same targets, seed and settings give the same answers whatever the order,
the batch size or how a stopped refine was resumed from its log.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError
from invphys.inverter.result import InversionResult
from invphys.inverter.seeds import target_seed
from invphys.inverter.simulate import masked_score

#: defaults: the polish's step and population (docs/inverting.md, "Polish on the simulator")
REFINE_POPSIZE = 8
REFINE_SIGMA0 = 0.012
#: the refine strategies (the first is the default) and their default number of known (stored) starts
REFINE_STRATEGIES = ("corrected", "cma")
KNOWN_STARTS = {"cma": 0, "corrected": 8}
#: a refined answer below this simulated R_actual is flagged
LOW_R_ACTUAL = 0.5
#: a target's refine stops once its best simulated R_actual reaches this (0 or 1: never)
REFINE_STOP = 0.98
#: the stall rule's gain when ``patience`` is given alone (off by default: patience 0; see docs/inverting.md)
REFINE_MIN_GAIN = 0.01


def refine(inv: Any, items: list[InversionResult], budget: int, popsize: int = REFINE_POPSIZE,
           sigma0: float = REFINE_SIGMA0, overrides: Mapping[str, Any] | None = None, batch_size: int | None = None,
           log: str | Path | None = None, seed: int = 0, on_run: Callable[[int, bool], None] | None = None,
           simulator: Any = None, extract_workers: int = 0, strategy: str = REFINE_STRATEGIES[0],
           known_starts: int | None = None, strategy_options: Mapping[str, Any] | None = None,
           stop: float = REFINE_STOP, ask_workers: int = 1, extract_threads: int | None = 1,
           patience: int | None = 0, min_gain: float = REFINE_MIN_GAIN,
           cost_budget: float | str | None = None) -> list[dict[str, Any]]:
    """Refine ``items`` in place (answer first); return one record per result (runs, seconds, R before/after).

    ``budget``: simulator runs per target, its unsimulated candidates included; ``batch_size``: runs in
    flight at once (None: the simulator's own); ``log``: a refine log (``.npz``) that a re-run replays;
    ``simulator``: use this simulator object instead of building the bundle's (e.g. one already warm);
    ``extract_workers``: extract features in this many worker processes while the simulator goes on (0: in
    this process, between launches); the answers are the same either way. ``strategy``: ``cma`` or
    ``corrected``; ``known_starts``: stored training rows added as free starts (None: the strategy's default);
    ``strategy_options``: ``corrected``'s settings by name
    (:class:`~invphys.evaluators.corrected_refine.CorrectedSettings`; its ``popsize`` is ``popsize``).
    ``stop``: a target asks for no more runs once its best simulated R_actual reaches it (0 or 1: never); the
    record's ``runs`` says how many it used and ``stopped`` whether it stopped early. ``ask_workers``: threads
    that tell and ask the searches while the simulator runs (0: between launches; the answers are the same);
    ``extract_threads``: native threads per extraction worker (None: one per core). ``patience`` (runs; 0 or
    None: off) and ``min_gain``: a target stalls, and asks no more runs, once its best R_actual gained less than
    ``min_gain`` over its last ``patience`` told runs (record: ``stalled``; ``batches``: the sizes of its told
    generations in order, so a replay of ``best_r_by_run`` knows where it could have stopped). ``cost_budget``
    (typical runs; None: off): a target spends at most this estimated simulator cost (:func:`run_costs`), so
    targets whose runs are slow (near the box's faces) get fewer runs (record: ``capped``; ``cost`` and
    ``cost_by_run``, recorded wherever the simulator estimates run costs, cap or not); ``"budget"``: as many
    typical runs as ``budget``, where the simulator estimates run costs (else off).
    """
    from invphys.evaluators.refine_log import RunLog
    from invphys.evaluators.stream_refine import check_stall, feed_features, log_key, stream_refine

    if not is_count(budget, 1, 100_000):
        raise InvphysError(f"refine budget must be a whole number in 1 .. 100000 runs per target, got {budget!r}")
    if batch_size is not None and (isinstance(batch_size, bool) or int(batch_size) < 1):
        raise InvphysError(f"batch size must be >= 1, got {batch_size!r}")
    known_starts = _check_strategy(strategy, known_starts)
    stop = check_stop(stop)
    patience, min_gain = check_stall(patience, min_gain)
    sim = simulator if simulator is not None else inv.simulator(overrides)
    cost = _cost(sim, cost_budget, budget)
    ext = inv.extractor(sim)
    m = inv.bundle.manifest
    key = log_key({"bundle": m.get("bundle_id", ""), "files": m.get("files", {}),
                   "simulator": m["simulator"].get("config", {}), "overrides": dict(overrides or {}),
                   "version": getattr(sim, "version", "")})
    runlog = None if log is None else RunLog(log, key, flush=int(batch_size or 16))
    stored = _stored_rows(inv) if known_starts or strategy == "corrected" else None
    targets = [_target(inv, r, budget, popsize, sigma0, seed, strategy, stored, known_starts, strategy_options)
               for r in items]
    search = _strategy(inv, strategy, popsize, sigma0, stored, strategy_options)
    pool = _extraction_pool(ext, extract_workers, extract_threads)
    stats: dict[str, float] = {}
    t0 = time.perf_counter()
    try:
        stream_refine(targets, feed_features(sim, ext, batch_size, pool), masked_score(inv), budget, popsize,
                      sigma0, log=runlog, on_run=on_run, strategy=search, stop=stop, ask_workers=ask_workers,
                      stats=stats, patience=patience, min_gain=min_gain, cost=cost)
    finally:
        if pool is not None:
            pool.close()
    wall = time.perf_counter() - t0
    records = []
    for r, t in zip(items, targets, strict=True):
        records.append(_apply(inv, r, t, budget, {"popsize": popsize, "sigma0": sigma0, "seed": seed,
                                                   "strategy": strategy, "known_starts": known_starts, "stop": stop,
                                                   "patience": patience, "min_gain": min_gain,
                                                   "cost_budget": _cap(cost),
                                                   **({"options": dict(strategy_options)} if strategy_options else {})}))
    call = _call_record(targets, wall, stats, ask_workers, extract_threads if extract_workers else None, log)
    for rec in records:
        rec["call"] = call
    return records


#: the parameter-box sample whose mean estimated run cost is one typical run (fixed: costs never change)
COST_REFERENCE_ROWS, COST_REFERENCE_SEED = 256, 0


def run_costs(sim: Any) -> Callable[[np.ndarray], np.ndarray] | None:
    """Each normalised point's estimated run cost in typical runs, from ``sim``'s
    :meth:`~invphys.core.interfaces.Simulator.estimate_cost`: a run's cost over the mean cost of a fixed
    uniform sample of the parameter box (so 1.0 is an average run); None where the simulator estimates none."""
    space = sim.parameter_space()
    ref = np.random.default_rng(COST_REFERENCE_SEED).random((COST_REFERENCE_ROWS, space.dim))
    est = sim.estimate_cost(space.denormalize(ref))
    if est is None:
        return None
    typical = float(np.mean(np.asarray(est, float)))
    if not (np.isfinite(typical) and typical > 0):
        raise InvphysError(f"the simulator's estimated run cost is not a positive number ({typical!r})")

    def of(points: np.ndarray) -> np.ndarray:
        c = np.asarray(sim.estimate_cost(space.denormalize(np.clip(points, 0.0, 1.0))), float).reshape(-1)
        if c.shape != (len(points),):
            raise InvphysError(f"the simulator's estimate_cost gave {c.shape[0]} costs for {len(points)} rows")
        if not np.all(np.isfinite(c) & (c >= 0)):
            raise InvphysError("the simulator's estimate_cost gave a negative or non-finite run cost")
        return c / typical

    return of


def run_cost(sim: Any, budget: Any) -> Any:
    """A :class:`~invphys.evaluators.stream_refine.RunCost` of ``budget`` typical runs (:func:`run_costs`); one
    error line when the simulator estimates no cost or the budget is not a positive number."""
    from invphys.evaluators.stream_refine import RunCost

    if isinstance(budget, bool) or not isinstance(budget, (int, float, np.integer, np.floating)) \
            or not 0 < float(budget) <= 1e9:
        raise InvphysError(f"refine cost budget must be a number of typical runs in (0, 1e9], got {budget!r}")
    of = run_costs(sim)
    if of is None:
        raise InvphysError(f"simulator {getattr(sim, 'name', type(sim).__name__)!r} estimates no run cost "
                           "(Simulator.estimate_cost), so a refine cost budget cannot apply to it")
    return RunCost(of, float(budget))


def _cost(sim: Any, cost_budget: float | str | None, budget: int) -> Any:
    """The refine's :class:`~invphys.evaluators.stream_refine.RunCost`: ``cost_budget`` typical runs
    (``"budget"``: ``budget``), or none that only records the costs; None where the simulator estimates none
    (then ``"budget"`` is off, and a number one error line)."""
    from invphys.evaluators.stream_refine import RunCost

    if cost_budget is not None and cost_budget != "budget":
        return run_cost(sim, cost_budget)
    of = run_costs(sim)
    if of is None:
        return None
    return RunCost(of, float(budget) if cost_budget == "budget" else math.inf)


def _call_record(targets: list[Any], wall: float, stats: dict[str, float], ask_workers: int,
                 extract_threads: int | None, log: str | Path | None) -> dict[str, Any]:
    """What one refine call did, over all its targets (every record's ``call``)."""
    return {"targets": len(targets), "runs": sum(t.runs for t in targets),
            "replayed_runs": sum(t.replayed for t in targets),
            "simulator_s": float(sum(t.seconds for t in targets)), "wall_time_s": wall,
            "ask_s": float(sum(t.ask_s for t in targets)), "ask_cpu_s": float(sum(t.ask_cpu_s for t in targets)),
            "ask_wait_s": float(stats.get("ask_wait_s", 0.0)), "ask_workers": int(ask_workers),
            "extract_threads": extract_threads, "stopped": int(sum(t.stopped for t in targets)),
            "stalled": int(sum(t.stalled for t in targets)), "capped": int(sum(t.capped for t in targets)),
            "log": None if log is None else str(log)}


def _cap(cost: Any) -> float | None:
    """The cost budget a refine applied (None: none)."""
    return None if cost is None or not np.isfinite(cost.budget) else float(cost.budget)


def _extraction_pool(extractor: Any, workers: int, threads: int | None = 1) -> Any:
    if not is_count(workers, 0, 256):
        raise InvphysError(f"extract workers must be a whole number in 0 .. 256, got {workers!r}")
    if not workers:
        return None
    from invphys.plugins.executors._extract_pool import ExtractionPool

    return ExtractionPool(extractor, int(workers), threads=threads)


def check_stop(stop: Any) -> float:
    """``stop`` as a float in [0, 1] (0 or 1: never stop), else one error line."""
    from invphys.evaluators.stream_refine import in_unit_interval

    if not in_unit_interval(stop):
        raise InvphysError(f"refine stop must be an R_actual in [0, 1] (0 or 1: never stop), got {stop!r}")
    return float(stop)


def _check_strategy(strategy: str, known_starts: int | None) -> int:
    if strategy not in REFINE_STRATEGIES:
        raise InvphysError(f"unknown refine strategy {strategy!r} (choose from: {', '.join(REFINE_STRATEGIES)})")
    if known_starts is None:
        return KNOWN_STARTS[strategy]
    if not is_count(known_starts, 0, 10_000):
        raise InvphysError(f"known starts must be a whole number in 0 .. 10000, got {known_starts!r}")
    return int(known_starts)


def _stored_rows(inv: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """The bundle's training rows (theta normalised, real features), None when it holds none."""
    from invphys.inverter.bundle import BundleError

    try:
        theta, y = inv.bundle.data("train")
    except BundleError:
        return None
    return theta, y


def _strategy(inv: Any, strategy: str, popsize: int, sigma0: float,
              stored: tuple[np.ndarray, np.ndarray] | None, options: Mapping[str, Any] | None = None) -> Any:
    """The search after the starts (None: stream_refine's CMA-ES with ``popsize`` and ``sigma0``)."""
    if strategy == "cma":
        if options:
            raise InvphysError("refine strategy 'cma' takes no options (its popsize and sigma0 are arguments)")
        return None
    from invphys.evaluators.corrected_refine import CorrectedSearch, corrected_settings, row_residuals

    def predict(theta: np.ndarray) -> np.ndarray:
        return np.asarray(inv.bundle.surrogate.predict(theta), float)

    rows = None if stored is None else row_residuals(predict, *stored)
    settings, score = corrected_settings({**dict(options or {}), "popsize": popsize}), masked_score(inv)
    return lambda t, _left: _OwnThreads(CorrectedSearch(t, predict, score, rows, settings),
                                          getattr(inv, "threads", 1))


class _OwnThreads:
    """A search whose asks and tells run with the inverter's BLAS threads (one by default: the surrogate's
    small products wait on each other on a busy CPU, e.g. beside extraction workers: measured 11-13 against
    31-42 ms a batch with two refines on 2 cores; 9 against 11 ms on an idle one)."""

    def __init__(self, search: Any, threads: int | None) -> None:
        self.search, self.threads = search, threads

    def ask(self, left: int) -> np.ndarray:
        from invphys.inverter.inverter import blas_threads

        with blas_threads(self.threads):
            return np.asarray(self.search.ask(left))

    def tell(self, points: np.ndarray, ys: np.ndarray, scores: np.ndarray, before: float) -> None:
        self.search.tell(points, ys, scores, before)


def _known_rows(inv: Any, stored: tuple[np.ndarray, np.ndarray] | None, target: np.ndarray, k: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` stored rows whose REAL features fit ``target`` best (NaN: a feature not given), best first."""
    d, m = inv.bundle.space.dim, len(inv.feature_names)
    if stored is None or k <= 0:
        return np.empty((0, d)), np.empty((0, m))
    theta, y = stored
    ok = np.all(np.isfinite(y), axis=1)
    sc = np.where(ok, masked_score(inv)(np.where(ok[:, None], y, 0.0), np.tile(target, (len(y), 1))), -np.inf)
    best = np.argsort(-sc, kind="stable")[:k]
    best = best[np.isfinite(sc[best])]
    return theta[best], y[best]


def _target(inv: Any, r: InversionResult, budget: int, popsize: int, sigma0: float, seed: int,
            strategy: str = "cma", stored: tuple[np.ndarray, np.ndarray] | None = None, known_starts: int = 0,
            options: Mapping[str, Any] | None = None) -> Any:
    """The refine of result ``r``: its candidates as starts (simulated ones with their features), then the
    ``known_starts`` best stored rows (their features known: no run)."""
    from invphys.evaluators.stream_refine import TargetRefine, log_key

    mf = len(inv.feature_names)
    starts = np.array([c.theta for c in r.candidates], dtype=np.float64)
    known = np.array([c.actual if c.actual is not None and c.r_actual is not None and np.isfinite(c.r_actual)
                      else np.full(mf, np.nan) for c in r.candidates], dtype=np.float64)
    target = np.where(r.mask, r.target, np.nan)
    rows_theta, rows_y = _known_rows(inv, stored, target, known_starts)
    starts, known = np.vstack([starts, rows_theta]), np.vstack([known, rows_y])
    s = target_seed(seed, "sim-refine", r.target, r.mask, f"{budget}/{popsize}/{sigma0!r}")
    parts = {"target": np.where(r.mask, r.target, 0.0).tolist(), "mask": np.asarray(r.mask).tolist(),
             "starts": starts.tolist(), "seed": s, "popsize": popsize, "sigma0": sigma0}
    if strategy != "cma":   # the cma key stays what it was, so older logs replay
        parts["strategy"] = strategy
        parts["options"] = dict(options or {})
    return TargetRefine(tid=log_key(parts), target=target, starts=starts, known=known, seed=s)


def _apply(inv: Any, r: InversionResult, t: Any, budget: int, settings: dict[str, Any]) -> dict[str, Any]:
    """Put the refined answer first: a start candidate (moved first, its simulation filled in) or a new
    candidate ``"<best start's source> + sim-refine"`` (a stored row's source: ``training row``); a warning
    when its simulated R_actual is below :data:`LOW_R_ACTUAL`; the record of what was done."""
    from invphys.core.masked_recovery import masked_recovery

    b = inv.bundle
    n = len(r.candidates)
    for c, y in zip(r.candidates, t.known[:n], strict=True):  # starts simulated by the refine: their R_actual
        if c.r_actual is None and np.all(np.isfinite(y)):
            c.actual = y.copy()
            c.r_actual = float(masked_recovery(y, r.target, b.scales, r.mask, b.kappa))
            c.gap = c.r_surrogate - c.r_actual
    scores = t.start_scores if t.start_scores is not None else np.full(len(t.starts), np.nan)
    first = float(scores[0]) if len(scores) and np.isfinite(scores[0]) else float("nan")
    best_start = int(np.nanargmax(scores)) if np.isfinite(scores).any() else 0
    start_r = float(scores[best_start]) if np.isfinite(scores).any() else float("nan")
    source = r.candidates[best_start].source if best_start < n else "training row"
    improved = False
    if t.best_index >= 0 and np.isfinite(t.score):
        j = next((j for j, c in enumerate(r.candidates) if np.array_equal(c.theta, t.theta)), None)
        if j is not None:
            r.candidates.insert(0, r.candidates.pop(j))
        else:
            stored = any(np.array_equal(t.theta, x) for x in t.starts[n:])
            label = "training row" if stored else f"{source} + sim-refine"
            cand = inv._calibrate_error_bars(inv._candidates(t.theta[None, :], [label], r.target, r.mask))[0]
            cand.actual, cand.r_actual = t.features.copy(), float(t.score)
            cand.gap = cand.r_surrogate - cand.r_actual
            r.candidates.insert(0, cand)
            improved = True
    warning = None
    if not (np.isfinite(t.score) and t.score >= LOW_R_ACTUAL):
        got = f"{t.score:.3f}" if np.isfinite(t.score) else "none (every run failed)"
        warning = (f"the refined answer's simulated R_actual is {got}, below {LOW_R_ACTUAL}: the simulator "
                   "reproduces this target poorly (a target outside what it can make, or more runs needed)")
        r.warnings.append(warning)

    def f(v: float) -> float | None:  # JSON has no NaN: a failed simulation is None
        return float(v) if np.isfinite(v) else None

    return {"budget": budget, "runs": t.runs, "stopped": t.stopped, "stalled": t.stalled, "capped": t.capped,
            "cost": t.cost, "cost_by_run": [float(c) for c in t.costs], "batches": list(t.batches),
            "replayed_runs": t.replayed, "generations_back_s": [round(v, 3) for v in t.back_s],
            "simulator_s": t.seconds, "ask_s": t.ask_s, "ask_cpu_s": t.ask_cpu_s, "r_answer": f(first),
            "start_source": source, "start_r_actual": f(start_r),
            "r_actual": f(t.score), "improved": improved, "known_starts": int(len(t.starts) - n), "warning": warning,
            "best_r_by_run": [f(v) for v in best_by_run(t)],
            "best_r_free": f(t.bests[0]) if t.bests else None, "settings": settings}


def best_by_run(t: Any) -> np.ndarray:
    """The best simulated R_actual of target ``t`` after each of its runs in ask order (its starts known at no
    run count from the first; -inf: none yet)."""
    scores = np.array([p[1] for p in t.points], float)
    free = len(scores) - t.runs
    if not t.runs:
        return np.empty(0)
    head = np.max(scores[:free]) if free else -np.inf
    return np.maximum.accumulate(np.concatenate([[head], scores[free:]]))[1:]
