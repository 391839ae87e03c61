"""Which per-target search refines best on the simulator at equal budgets (16, 32, 64 runs per target)?

Answers the first ``--limit`` rows of each target store (``--sets NAME=STORE ...``) with the bundle (its
top ``--starts`` candidates, the amortised answer first), then refines every target with every method of
``--methods`` on one warm simulator and records the best R_actual so far after each of ``--budgets`` runs:

- ``cma``: the streaming CMA-ES refine as ``invphys invert --sim-refine N`` runs it
  (:mod:`invphys.evaluators.stream_refine`: its starts, then ask/tell CMA-ES from the best of them,
  popsize ``--q``, step ``--sigma0``);
- ``corrected``: the default refine's search (``--sim-refine``: the surrogate corrected by the target's runs
  and the bundle's nearest training rows, :mod:`invphys.evaluators.corrected_refine`), from the same starts
  (no stored rows added as starts here), popsize ``--q``;
- ``optuna_tpe``, ``optuna_cmaes``, ``optuna_gp``: Optuna's TPE, CMA-ES (x0 the best start, the same step)
  and GP samplers with their default settings, seeded with every simulated start that lies in the box
  (``study.add_trial`` with its known R: ``enqueue_trial`` would simulate it again);
- ``botorch_qlogei``: a SingleTaskGP on the target's runs so far in the box (the best start included)
  and qLogExpectedImprovement, ``--q`` points per round (``optimize_acqf``, 4 restarts, 256 raw samples).

Budget: every method first simulates the same start candidates (each counts one run, as
``stream_refine`` counts them), then asks ``--q`` points per round until it has spent the budget.
Search box: the same for every method, ``[best start - box, best start + box]`` in the normalised
``[0, 1]^d`` cube (clipped to it), ``--box`` 1 for the whole cube; ``cma``'s points are clipped to it
too (at ``--sigma0`` 0.012 this rarely binds; the JSON counts the clipped points). Objective: R over
the target's features (:func:`invphys.inverter.simulate.masked_score`, what validation reports); a
failed run scores 0 for the searches and in the means.

Every method's and target's rows share ONE open stream (``Simulator.simulate_feed``): a search's next
round joins as soon as its own runs are back, its features extracted in ``--extract-workers`` processes
(:class:`ExtractionPool`, as dataset generation does: in the simulating process extraction costs ~0.14
s per paper run between launches) and the model searches' next rounds (GP fits) computed in
``--ask-procs`` processes, one torch thread each, while the simulator goes on. A round is told in ask
order and each search draws from its own seed (target, method, ``--seed``; a model search's round from
that seed and the round's number: ``optuna_gp``'s study is rebuilt each round from the runs), so the
answers depend neither on completion order, the batch size, the processes nor the other targets. Rounds
end on multiples of ``--q`` runs (the first after the starts is shorter), so 16, 32 and 64 end rounds;
``cma`` keeps its own generations (the starts, then popsize ``--q``): its best after a budget counts a
generation's runs in ask order. The JSON (``--out``) is rewritten after every round of the slowest
search and at the end: device, simulator, per set x method x budget the mean best R with a 95 %
bootstrap interval, the paired difference to ``cma`` with its interval, and per-target values. Example (GPU)::

    python benchmarks/bench_refine_budget.py --bundle inverters/orange_peel_paper \\
        --sets uniform=datasets/orange_peel_paper_fresh_uniform edge=datasets/orange_peel_paper_fresh_edge \\
        --limit 8 --budgets 16 32 64 --methods cma optuna_tpe optuna_gp botorch_qlogei \\
        --out benchmarks/results/refine_budget_paper_h100.json

``--first N --limit K`` runs one shard of the targets (rows N .. N+K-1 of each set), e.g. one per GPU; ``--merge
A.json B.json ... --out X.json`` joins shards run with the same settings into one table (per-target values in
row order, intervals and paired differences computed again).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, wait
from pathlib import Path
from typing import Any

import numpy as np

METHODS = ("cma", "corrected", "optuna_tpe", "optuna_cmaes", "optuna_gp", "botorch_qlogei")
_NEEDS = {"optuna_tpe": "optuna", "optuna_cmaes": "optuna", "optuna_gp": "optuna", "botorch_qlogei": "botorch"}


def _machine() -> Any:
    if str(Path(__file__).parent) not in sys.path:
        sys.path.insert(0, str(Path(__file__).parent))
    import _machine

    return _machine


class MissingPackage(SystemExit):
    pass


def check_packages(methods: list[str]) -> None:
    """Exit with one clear line when a method's package is not installed."""
    import importlib.util

    for m in methods:
        if m not in METHODS:
            raise MissingPackage(f"error: unknown method {m!r} (choose from {', '.join(METHODS)})")
        pkg = _NEEDS.get(m)
        if pkg and importlib.util.find_spec(pkg) is None:
            raise MissingPackage(f"error: method {m} needs the package {pkg} (pip install 'invphys[bench]' or "
                                 f"pip install {pkg})")


# ---------------------------------------------------------------------------------------------- searches


class Search:
    """One (target, method): its starts, then ``q`` points per round in the box around its best start."""

    def __init__(self, key: tuple[str, int, str], target: np.ndarray, starts: np.ndarray, seed: int, budget: int,
                 q: int, box: float, sigma0: float) -> None:
        self.key, self.target, self.starts, self.seed = key, target, starts, int(seed)
        self.budget, self.q, self.box, self.sigma0 = budget, q, box, sigma0
        self.d = starts.shape[1]
        self.history: list[tuple[np.ndarray, float]] = []   # (point, R or -inf), in tell order
        self.start_scores: np.ndarray | None = None
        self.lo = self.hi = None
        self.clipped = self.fallbacks = self.warnings = 0
        self.ask_s = 0.0
        self.rounds = 0

    @property
    def runs(self) -> int:
        return len(self.history)

    def first(self) -> np.ndarray:
        """The starts (each one run), cut to the budget."""
        return self.starts[:self.budget]

    def tell_starts(self, scores: np.ndarray, ys: np.ndarray) -> None:
        self.start_scores = np.full(len(self.starts), np.nan)
        self.start_scores[:len(scores)] = np.where(np.isfinite(scores), scores, np.nan)
        for x, s in zip(self.starts, scores, strict=False):
            self.history.append((x.copy(), float(s)))
        best = int(np.argmax(scores)) if len(scores) and np.isfinite(scores).any() else 0
        c = self.starts[best]
        self.center = c.copy()
        self.lo, self.hi = np.clip(c - self.box, 0.0, 1.0), np.clip(c + self.box, 0.0, 1.0)

    def ask(self, n: int) -> np.ndarray:
        raise NotImplementedError

    def tell(self, x: np.ndarray, scores: np.ndarray, ys: np.ndarray) -> None:
        for p, s in zip(x, scores, strict=True):
            self.history.append((p.copy(), float(s)))
        self._tell(x, scores)

    def _tell(self, x: np.ndarray, scores: np.ndarray) -> None:
        pass

    def random(self, n: int, round_: int) -> np.ndarray:
        """Seeded uniform points in the box (a model that cannot fit falls back to these; counted)."""
        rng = np.random.default_rng([self.seed, round_])
        self.fallbacks += n
        assert self.lo is not None and self.hi is not None
        return self.lo + rng.random((n, self.d)) * (self.hi - self.lo)

    def best_after(self, runs: int) -> float:
        s = [v for _x, v in self.history[:runs]]
        best = max(s) if s else 0.0
        return float(best) if np.isfinite(best) else 0.0


class CmaSearch(Search):
    """``stream_refine``'s own search (its ``_Search``: CMA-ES from the best start), popsize ``q``, told
    through ``stream_refine``'s own bookkeeping (runs, points, start scores, the CMA-ES state)."""

    def bind(self, target_refine: Any, score: Callable[[np.ndarray, np.ndarray], np.ndarray],
             strategy: Any = None) -> None:
        from invphys.evaluators.stream_refine import _Search, _start_known

        self.t, self.score = target_refine, score
        self.s = _Search(target_refine, self.budget, self.q, self.sigma0, self.d, strategy)
        _start_known(self.s, score)   # as stream_refine does first (no start is simulated yet here)

    def first(self) -> np.ndarray:
        self._starts = self.s.next_points()
        return self._starts

    def tell_starts(self, scores: np.ndarray, ys: np.ndarray) -> None:
        self._told(self._starts, ys)
        super().tell_starts(scores, ys)   # the box around the best start (stream_refine's start: the same)
        self.history = [(p.copy(), float(v)) for p, v, _y in self.t.points]

    def _told(self, pts: np.ndarray, ys: np.ndarray) -> None:
        from invphys.evaluators.stream_refine import _tell

        self.s.asked = pts
        self.s.results = [(np.asarray(y, float), 0.0, "", False) for y in ys]
        _tell(self.s, self.score, lambda _n, _r: None)

    def ask(self, n: int) -> np.ndarray:
        pts = np.asarray(self.s.next_points(), float)[:n]
        assert self.lo is not None and self.hi is not None
        boxed = np.clip(pts, self.lo, self.hi)
        self.clipped += int(np.any(boxed != pts, axis=1).sum())
        return boxed

    def tell(self, x: np.ndarray, scores: np.ndarray, ys: np.ndarray) -> None:
        self._told(x, ys)
        self.history = [(p.copy(), float(v)) for p, v, _y in self.t.points]


class OptunaSearch(Search):
    """An Optuna sampler (default settings, seeded) on the box, told every simulated start inside it."""

    kind = "tpe"

    def _study(self) -> Any:
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        assert self.lo is not None and self.hi is not None
        self.dists = {f"x{i}": optuna.distributions.FloatDistribution(float(self.lo[i]), float(self.hi[i]))
                      for i in range(self.d)}
        if self.kind == "tpe":
            sampler: Any = optuna.samplers.TPESampler(seed=self.seed)
        elif self.kind == "gp":
            sampler = optuna.samplers.GPSampler(seed=self.seed)
        else:   # the same start and step as ``cma`` (Optuna's CMA-ES works in the box scaled to [0, 1])
            width = float(np.min(self.hi - self.lo)) or 1.0
            sampler = optuna.samplers.CmaEsSampler(x0={k: float(v) for k, v in zip(self.dists, self.center,
                                                                                    strict=True)},
                                                   sigma0=self.sigma0 / width, popsize=self.q, seed=self.seed)
        study = optuna.create_study(direction="maximize", sampler=sampler)
        for x, s in self.history:   # the starts
            if np.all(x >= self.lo) and np.all(x <= self.hi):
                study.add_trial(optuna.trial.create_trial(
                    params={k: float(v) for k, v in zip(self.dists, x, strict=True)}, distributions=self.dists,
                    value=float(s) if np.isfinite(s) else 0.0))
        self.trials: list[Any] = []
        return study

    def ask(self, n: int) -> np.ndarray:
        if not hasattr(self, "study"):
            self.study = self._study()
        self.trials = [self.study.ask(self.dists) for _ in range(n)]
        return np.array([[t.params[k] for k in self.dists] for t in self.trials], float)

    def _tell(self, x: np.ndarray, scores: np.ndarray) -> None:
        for t, s in zip(self.trials, scores, strict=True):
            self.study.tell(t, float(s) if np.isfinite(s) else 0.0)


class OptunaTPE(OptunaSearch):
    kind = "tpe"


class OptunaCMAES(OptunaSearch):
    kind = "cmaes"


class ModelSearch(Search):
    """A search whose round is a pure function of its runs so far (a model refitted every round): the ask is
    a job (function, arguments) that a worker process can run, seeded by (search seed, round)."""

    def data(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.array([p for p, _s in self.history])
        y = np.array([s if np.isfinite(s) else 0.0 for _p, s in self.history])
        return x, y

    def job(self, n: int) -> tuple[Callable[..., np.ndarray], tuple[Any, ...]]:
        raise NotImplementedError

    def ask(self, n: int) -> np.ndarray:
        fn, args = self.job(n)
        pts, fallbacks = fn(*args)
        self.fallbacks += fallbacks
        return pts


class OptunaGP(ModelSearch):
    """Optuna's GPSampler (default settings), its study rebuilt each round from every run in the box."""

    def job(self, n: int) -> tuple[Callable[..., np.ndarray], tuple[Any, ...]]:
        self.rounds += 1
        x, y = self.data()
        return optuna_gp_points, (x, y, self.lo, self.hi, _round_seed(self.seed, self.rounds), n)


class BoTorchQLogEI(ModelSearch):
    """SingleTaskGP (inputs scaled to the box, outcomes standardised) + qLogEI, ``n`` points per round."""

    #: optimize_acqf's effort (restarts, raw samples, L-BFGS-B iterations) and the qMC samples
    restarts, raw_samples, maxiter, mc_samples = 4, 256, 100, 128

    def job(self, n: int) -> tuple[Callable[..., np.ndarray], tuple[Any, ...]]:
        self.rounds += 1
        x, y = self.data()
        return botorch_points, (x, y, self.lo, self.hi, _round_seed(self.seed, self.rounds), n,
                                (self.restarts, self.raw_samples, self.maxiter, self.mc_samples))


def _round_seed(seed: int, round_: int) -> int:
    return int(np.random.SeedSequence([seed, round_]).generate_state(1)[0])


def _in_box(x: np.ndarray, y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    return x[inside], y[inside]


def optuna_gp_points(x: np.ndarray, y: np.ndarray, lo: np.ndarray, hi: np.ndarray, seed: int, n: int
                     ) -> tuple[np.ndarray, int]:
    """``n`` points from Optuna's GPSampler told every run in the box (the earlier ones are its history)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    dists = {f"x{i}": optuna.distributions.FloatDistribution(float(lo[i]), float(hi[i])) for i in range(len(lo))}
    study = optuna.create_study(direction="maximize", sampler=optuna.samplers.GPSampler(seed=seed))
    for p, v in zip(*_in_box(x, y, lo, hi), strict=True):
        study.add_trial(optuna.trial.create_trial(params={k: float(c) for k, c in zip(dists, p, strict=True)},
                                                  distributions=dists, value=float(v)))
    trials = [study.ask(dists) for _ in range(n)]
    return np.array([[t.params[k] for k in dists] for t in trials], float), 0


def botorch_points(x: np.ndarray, y: np.ndarray, lo: np.ndarray, hi: np.ndarray, seed: int, n: int,
                   effort: tuple[int, int, int, int]) -> tuple[np.ndarray, int]:
    """``n`` points maximising qLogEI of a SingleTaskGP fitted to the runs in the box (seeded random points in
    the box, counted, when the GP cannot be fitted)."""
    import torch
    from botorch.acquisition.logei import qLogExpectedImprovement
    from botorch.fit import fit_gpytorch_mll
    from botorch.models import SingleTaskGP
    from botorch.models.transforms.outcome import Standardize
    from botorch.optim import optimize_acqf
    from botorch.sampling.normal import SobolQMCNormalSampler
    from gpytorch.mlls import ExactMarginalLogLikelihood

    restarts, raw, maxiter, mc = effort
    d = len(lo)
    x, y = _in_box(x, y, lo, hi)   # as Optuna's study: the runs in the box (the best start always is)
    width = np.maximum(hi - lo, 1e-12)
    torch.manual_seed(seed)
    try:
        tx = torch.tensor((x - lo) / width, dtype=torch.float64)
        ty = torch.tensor(y[:, None], dtype=torch.float64)
        model = SingleTaskGP(tx, ty, outcome_transform=Standardize(m=1))
        fit_gpytorch_mll(ExactMarginalLogLikelihood(model.likelihood, model))
        acq = qLogExpectedImprovement(model, best_f=ty.max(), sampler=SobolQMCNormalSampler(torch.Size([mc]),
                                                                                              seed=seed))
        bounds = torch.stack([torch.zeros(d), torch.ones(d)]).to(torch.float64)
        cand, _v = optimize_acqf(acq, bounds=bounds, q=n, num_restarts=restarts, raw_samples=raw,
                                 options={"seed": seed, "maxiter": maxiter})
        pts = lo + cand.detach().numpy() * width
        if not np.all(np.isfinite(pts)):
            raise ValueError("non-finite candidates")
        return np.clip(pts, lo, hi), 0
    except Exception:   # a GP that cannot be fitted: seeded random points in the box (counted)
        return lo + np.random.default_rng(seed).random((n, d)) * (hi - lo), n


def run_job(fn: Callable[..., tuple[np.ndarray, int]], args: tuple[Any, ...]) -> tuple[np.ndarray, int, int, float]:
    """``fn(*args)`` on one torch thread with every warning recorded (BoTorch's fit retries on the warnings it
    records: the answer must not depend on the caller's filters); (points, fallbacks, warnings, seconds)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            pts, fallbacks = fn(*args)
    finally:
        torch.set_num_threads(threads)
    return pts, fallbacks, len(caught), time.perf_counter() - t0


CLASSES: dict[str, type[Search]] = {"cma": CmaSearch, "optuna_tpe": OptunaTPE, "optuna_cmaes": OptunaCMAES,
                                    "optuna_gp": OptunaGP, "botorch_qlogei": BoTorchQLogEI}


# ---------------------------------------------------------------------------------------------- the stream


class Stream:
    """Every search's rounds through one open ``simulate_feed`` stream (see the module's text)."""

    def __init__(self, searches: list[Search], simulate_feed: Callable[..., Any], extract: Callable[[Any], Any],
                 score: Callable[[np.ndarray, np.ndarray], np.ndarray], ask_procs: int = 0,
                 on_round: Callable[[], None] | None = None) -> None:
        self.searches, self.feed, self.extract, self.score = searches, simulate_feed, extract, score
        self.procs = _ask_pool(ask_procs) if ask_procs else None
        self.on_round = on_round or (lambda: None)
        self.queue: list[tuple[int, int]] = []
        self.fed: list[tuple[int, int]] = []
        self.asked: list[np.ndarray | None] = [None] * len(searches)
        self.results: list[list[Any]] = [[] for _ in searches]
        self.phase = ["starts"] * len(searches)
        self.pending: dict[Future, tuple[str, Any]] = {}
        self.back = 0
        self.round_mark = 0
        self.sim_wall = 0.0

    def run(self) -> None:
        for k, s in enumerate(self.searches):
            self._queue(k, s.first())
        for i, res in self.feed(self._feeder):
            self.back += 1
            got = self.extract(res)
            if isinstance(got, Future):
                self.pending[got] = ("y", i)
            else:
                self._result(i, got)
            self._collect(block=False)
        if self.procs is not None:
            self.procs.shutdown(wait=True)
        left = [s.key for s in self.searches if s.runs < s.budget]
        if left or self.queue or self.pending:
            raise RuntimeError(f"the stream ended before every search spent its budget: {left[:3]}")

    def _queue(self, k: int, pts: np.ndarray) -> None:
        pts = np.asarray(pts, float).reshape(-1, self.searches[k].d)
        if len(pts) == 0:
            self.phase[k] = "done"
            return
        self.asked[k], self.results[k] = pts, [None] * len(pts)
        self.queue.extend((k, j) for j in range(len(pts)))

    def _feeder(self, free: int) -> np.ndarray | None:
        self._collect(block=False)
        while not self.queue and self.back == len(self.fed) and self.pending:
            self._collect(block=True)   # nothing runs: wait for features or asks still being computed
        if not self.queue:
            return None
        rows, self.queue = self.queue, []
        self.fed.extend(rows)
        return np.array([self.asked[k][j] for k, j in rows])  # type: ignore[index]

    def _collect(self, block: bool) -> None:
        if not self.pending:
            return
        done, _ = wait(list(self.pending), timeout=None if block else 0, return_when=FIRST_COMPLETED)
        for f in sorted(done, key=lambda f: self.pending[f][1] if self.pending[f][0] == "y" else -1):
            what, arg = self.pending.pop(f)
            if what == "y":
                self._result(arg, f.result())
            else:
                self._asked(arg, f.result())

    def _result(self, i: int, y: np.ndarray) -> None:
        k, j = self.fed[i]
        self.results[k][j] = y
        if any(r is None for r in self.results[k]):
            return
        s = self.searches[k]
        ys = np.array(self.results[k])
        sc = _scores(self.score, ys, s.target)
        pts = self.asked[k]
        assert pts is not None
        if self.phase[k] == "starts":
            s.tell_starts(sc, ys)
            self.phase[k] = "search"
        else:
            s.tell(pts, sc, ys)
        self._next(k)
        low = min(x.runs for x in self.searches)
        if low // max(1, self.searches[0].q) > self.round_mark or low == min(x.budget for x in self.searches):
            self.round_mark = low // max(1, self.searches[0].q)
            self.on_round()

    def _next(self, k: int) -> None:
        s = self.searches[k]
        n = min(s.q, s.budget - s.runs)
        if not isinstance(s, CmaSearch):   # rounds end on multiples of q (16, 32, 64 at q 8); cma: its popsize
            n = min(n, s.q - s.runs % s.q)
        if n <= 0:
            self.phase[k] = "done"
            return
        if not isinstance(s, ModelSearch):   # cheap: asked here (cma's package uses NumPy's global random state)
            self._asked(k, _plain_ask(s, n))
            return
        fn, args = s.job(n)
        if self.procs is None:
            self._asked(k, run_job(fn, args))
        else:
            self.pending[self.procs.submit(run_job, fn, args)] = ("ask", k)

    def _asked(self, k: int, out: tuple[np.ndarray, int, int, float]) -> None:
        s = self.searches[k]
        pts, fallbacks, warned, seconds = out
        s.fallbacks, s.warnings, s.ask_s = s.fallbacks + fallbacks, s.warnings + warned, s.ask_s + seconds
        if len(pts) != min(s.q, s.budget - s.runs, s.q - s.runs % s.q) and not isinstance(s, CmaSearch):
            raise RuntimeError(f"{s.key}: got {len(pts)} points for a round")
        self._queue(k, pts)


def _plain_ask(s: Search, n: int) -> tuple[np.ndarray, int, int, float]:
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pts = s.ask(n)
    return pts, 0, len(caught), time.perf_counter() - t0


def _ask_pool(n: int) -> Any:
    """``n`` worker processes for the model searches' rounds (spawned: no CUDA or Taichi state is forked)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    _machine()   # benchmarks/ on sys.path, which the spawned processes inherit (they import this module)
    return ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"))


def _scores(score: Callable[[np.ndarray, np.ndarray], np.ndarray], y: np.ndarray, target: np.ndarray) -> np.ndarray:
    from invphys.evaluators.stream_refine import _scores as scores

    return scores(score, y, target)


# ---------------------------------------------------------------------------------------------- statistics


def bootstrap(v: np.ndarray, n: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """Mean of ``v`` and its 95 % percentile bootstrap interval (resampling targets; seeded)."""
    v = np.asarray(v, float)
    if len(v) == 0:
        return float("nan"), float("nan"), float("nan")
    idx = np.random.default_rng(seed).integers(0, len(v), (n, len(v)))
    means = v[idx].mean(axis=1)
    return float(v.mean()), float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def table(searches: list[Search], budgets: list[int], n_boot: int = 2000) -> dict[str, Any]:
    """Per set x method x budget: mean best R (95 % interval), the paired difference to ``cma``, values."""
    out: dict[str, Any] = {}
    sets = sorted({s.key[0] for s in searches})
    for name in sets:
        by: dict[str, dict[int, Search]] = {}
        for s in searches:
            if s.key[0] == name:
                by.setdefault(s.key[2], {})[s.key[1]] = s
        rows: dict[str, Any] = {}
        for method, per in by.items():
            idx = sorted(per)
            first = per[idx[0]]
            rec: dict[str, Any] = {"targets": len(idx), "runs": [per[i].runs for i in idx],
                                   "clipped": sum(per[i].clipped for i in idx),
                                   "fallback_points": sum(per[i].fallbacks for i in idx),
                                   "ask_warnings": sum(per[i].warnings for i in idx),
                                   "ask_s": sum(per[i].ask_s for i in idx), "budgets": {}}
            ss = [np.nan_to_num(np.asarray(per[i].start_scores, float)) for i in idx
                  if per[i].start_scores is not None]
            if len(ss) == len(idx):   # the amortised answer (first start) and the best start, failures as 0
                for name_, v in (("r_answer", [x[0] for x in ss]), ("r_best_start", [x.max() for x in ss])):
                    m, lo, hi = bootstrap(np.array(v), n_boot)
                    rec[name_] = {"mean": m, "ci95": [lo, hi], "per_target": [float(x) for x in v]}
            for b in budgets:
                if any(per[i].runs < min(b, first.budget) for i in idx):
                    continue   # not every target has spent this budget yet
                v = np.array([per[i].best_after(b) for i in idx])
                m, lo, hi = bootstrap(v, n_boot)
                cell: dict[str, Any] = {"mean": m, "ci95": [lo, hi], "per_target": v.tolist()}
                ref = by.get("cma")
                if method != "cma" and ref is not None and sorted(ref) == idx and \
                        all(ref[i].runs >= min(b, ref[i].budget) for i in idx):
                    dv = v - np.array([ref[i].best_after(b) for i in idx])
                    dm, dlo, dhi = bootstrap(dv, n_boot, seed=1)
                    cell["vs_cma"] = {"mean": dm, "ci95": [dlo, dhi], "wins": int((dv > 0).sum()),
                                      "losses": int((dv < 0).sum())}
                rec["budgets"][str(b)] = cell
            rows[method] = rec
        out[name] = rows
    return out


#: settings every shard of one table must share
SHARD_KEYS = ("bundle", "answer_method", "sets", "methods", "budgets", "starts", "q", "box", "sigma0", "seed",
              "simulator_version", "simulator_config")


def merge_shards(shards: list[dict[str, Any]], n_boot: int = 2000) -> dict[str, Any]:
    """One result from shards that ran other targets (``--first``) with the same settings: per-target values
    joined in target order, means, intervals and paired differences to ``cma`` computed again."""
    shards = sorted(shards, key=lambda r: int(r.get("first", 0)))
    for r in shards[1:]:
        bad = [k for k in SHARD_KEYS if r.get(k) != shards[0].get(k)]
        if bad:
            raise SystemExit(f"error: --merge: the shards differ in {', '.join(bad)}")
    out = {k: v for k, v in shards[0].items() if k not in ("table", "first", "limit")}
    out.update(shards=[{k: r.get(k) for k in ("first", "limit", "device", "runs", "wall_s", "complete")}
                       for r in shards],
               complete=all(r.get("complete") for r in shards), runs=sum(r["runs"] for r in shards),
               wall_s=max(r["wall_s"] for r in shards), command=[r.get("command") for r in shards],
               ask_s={m: sum(r["ask_s"].get(m, 0.0) for r in shards) for m in shards[0]["methods"]})
    out["table"] = {name: {m: _merge_cell([r["table"].get(name, {}).get(m) for r in shards], n_boot)
                           for m in shards[0]["methods"]} for name in shards[0]["sets"]}
    for rows in out["table"].values():
        _paired(rows, n_boot)
    return out


def _merge_cell(cells: list[dict[str, Any] | None], n_boot: int) -> dict[str, Any]:
    cells = [c for c in cells if c]
    rec: dict[str, Any] = {"targets": sum(c["targets"] for c in cells), "runs": _joined(c["runs"] for c in cells),
                           "budgets": {}}
    for k in ("clipped", "fallback_points", "ask_warnings", "ask_s"):
        rec[k] = sum(c[k] for c in cells)
    for k in ("r_answer", "r_best_start"):
        if all(k in c for c in cells):
            v = np.array(_joined(c[k]["per_target"] for c in cells))
            m, lo, hi = bootstrap(v, n_boot)
            rec[k] = {"mean": m, "ci95": [lo, hi], "per_target": v.tolist()}
    for b in cells[0]["budgets"] if cells else []:
        if all(b in c["budgets"] for c in cells):   # a budget counts once every shard's targets spent it
            v = np.array(_joined(c["budgets"][b]["per_target"] for c in cells))
            m, lo, hi = bootstrap(v, n_boot)
            rec["budgets"][b] = {"mean": m, "ci95": [lo, hi], "per_target": v.tolist()}
    return rec


def _joined(lists: Any) -> list[Any]:
    return [x for part in lists for x in part]


def _paired(rows: dict[str, Any], n_boot: int) -> None:
    """Each method's paired difference to ``cma`` at every budget both have."""
    ref = rows.get("cma")
    for method, rec in rows.items():
        for b, cell in rec["budgets"].items():
            if method == "cma" or ref is None or b not in ref["budgets"]:
                continue
            dv = np.array(cell["per_target"]) - np.array(ref["budgets"][b]["per_target"])
            dm, dlo, dhi = bootstrap(dv, n_boot, seed=1)
            cell["vs_cma"] = {"mean": dm, "ci95": [dlo, dhi], "wins": int((dv > 0).sum()),
                              "losses": int((dv < 0).sum())}


# ---------------------------------------------------------------------------------------------- running


def _sets(items: list[str]) -> list[tuple[str, str]]:
    out = []
    for it in items:
        name, eq, path = it.partition("=")
        if not eq or not name or not path:
            raise SystemExit(f"error: --sets takes NAME=STORE items, got {it!r}")
        out.append((name, path))
    if len({n for n, _ in out}) != len(out):
        raise SystemExit("error: --sets names must differ")
    return out


def build_searches(inv: Any, sets: list[tuple[str, Any]], methods: list[str], budget: int, q: int, box: float,
                   sigma0: float, seed: int, first: int = 0) -> list[Search]:
    """One search per (set, target, method), all from the same start candidates of each result (targets
    numbered from ``first``: their row in the store)."""
    from invphys.inverter.refine import _target
    from invphys.inverter.seeds import target_seed
    from invphys.inverter.simulate import masked_score

    score = masked_score(inv)
    made: dict[str, Any] = {}

    def corrected(popsize: int, step: float) -> Any:
        """``--sim-refine``'s default search (the corrected surrogate, the bundle's training rows), made once;
        no stored rows join the starts here: every method starts from the same candidates."""
        if "corrected" not in made:
            from invphys.inverter.refine import _stored_rows, _strategy

            made["corrected"] = _strategy(inv, "corrected", popsize, step, _stored_rows(inv))
        return made["corrected"]

    searches: list[Search] = []
    for name, results in sets:
        for i, r in enumerate(results, start=first):
            starts = np.array([c.theta for c in r.candidates], dtype=np.float64)
            target = np.where(r.mask, r.target, np.nan)
            for m in methods:
                if m in ("cma", "corrected"):
                    t = _target(inv, r, budget, q, sigma0, seed)   # the seed --sim-refine gives this target
                    s: Search = CmaSearch((name, i, m), target, starts, t.seed, budget, q, box, sigma0)
                    s.bind(t, score, corrected(q, sigma0) if m == "corrected" else None)  # type: ignore[attr-defined]
                else:
                    sd = target_seed(seed, m, r.target, r.mask, f"refine-budget/{budget}/{q}/{box!r}")
                    s = CLASSES[m]((name, i, m), target, starts, sd, budget, q, box, sigma0)
                searches.append(s)
    return searches


def extractor_of(sim: Any, ext: Any, workers: int) -> tuple[Callable[[Any], Any], Any]:
    """``extract(result)`` -> features (NaN: failed) or a Future of them, and the pool to close (or None)."""
    from invphys.plugins.validators.simulator import SimulatorValidator

    m = len(ext.feature_names)

    def features(res: Any, fut: Any = None) -> np.ndarray:
        feats, _failure, _stats = SimulatorValidator._outcome(res, ext, m, fut)
        return np.full(m, np.nan) if feats is None else feats

    if workers <= 0:
        return features, None
    from invphys.plugins.executors._extract_pool import ExtractionPool

    pool = ExtractionPool(ext, workers)

    def submit(res: Any) -> Any:
        fut = pool.submit(res)
        if fut is None:
            return features(res)
        out: Future = Future()

        def done(f: Future) -> None:
            try:
                out.set_result(features(res, f))
            except BaseException as exc:  # the collector raises it (an InvphysError: the user's to fix)
                out.set_exception(exc)

        fut.add_done_callback(done)
        return out

    return submit, pool


def refine_all(sim: Any, ext: Any, searches: list[Search], score: Callable[[np.ndarray, np.ndarray], np.ndarray],
               batch: int | None, extract_workers: int = 0, ask_procs: int = 0,
               on_round: Callable[[], None] | None = None) -> Stream:
    """Run every search to its budget through one ``sim.simulate_feed`` stream; the stream (``fed``: which
    search's row each fed row was)."""
    extract, pool = extractor_of(sim, ext, extract_workers)
    stream = Stream(searches, lambda feeder: sim.simulate_feed(lambda free: _physical(sim, feeder(free)), batch),
                    extract, score, ask_procs, on_round)
    try:
        stream.run()
    finally:
        if pool is not None:
            pool.close()
    return stream


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--bundle", default="inverters/orange_peel_paper")
    p.add_argument("--sets", nargs="+", default=["uniform=datasets/orange_peel_paper_fresh_uniform",
                                                  "edge=datasets/orange_peel_paper_fresh_edge"],
                   help="NAME=STORE target stores")
    p.add_argument("--limit", type=int, default=8, help="targets per set (the first rows)")
    p.add_argument("--first", type=int, default=0, help="skip this many rows of each set first (with --limit: "
                                                        "one shard of the targets, e.g. one per GPU; --merge "
                                                        "joins the shards' JSONs)")
    p.add_argument("--merge", type=Path, nargs="+", default=None, help="join these shards' JSONs (same settings, "
                                                                      "other --first) into --out; no simulation")
    p.add_argument("--methods", nargs="+", default=["cma", "optuna_tpe", "optuna_gp", "botorch_qlogei"])
    p.add_argument("--budgets", type=int, nargs="+", default=[16, 32, 64], help="runs per target; the largest "
                                                                                 "is spent")
    p.add_argument("--starts", type=int, default=4, help="candidates per target every search starts from")
    p.add_argument("--q", type=int, default=8, help="points per round (cma: its popsize)")
    p.add_argument("--box", type=float, default=0.1, help="half-width of the search box around the best start "
                                                         "in the [0, 1] cube (1: the whole cube)")
    p.add_argument("--sigma0", type=float, default=0.012, help="cma's (and optuna_cmaes's) step in the cube")
    p.add_argument("--method", default=None, help="the bundle's answer method (default: its own)")
    p.add_argument("--sim-option", nargs="*", default=[], help="KEY=VALUE simulator overrides")
    p.add_argument("--sim-batch", type=int, default=64, help="runs in flight (slots)")
    p.add_argument("--extract-workers", type=int, default=4, help="feature-extraction processes (0: in process)")
    p.add_argument("--ask-procs", type=int, default=8, help="processes computing the model searches' rounds "
                                                           "(botorch_qlogei, optuna_gp; 0: in this process)")
    p.add_argument("--bootstrap", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    if a.merge:
        _machine().emit(merge_shards([json.loads(f.read_text()) for f in a.merge], a.bootstrap), a.out)
        return 0
    check_packages(a.methods)
    if a.q < 2 or a.starts < 1 or not 0 < a.box <= 1 or min(a.budgets) < 1 or a.limit < 1:
        raise SystemExit("error: --q >= 2, --starts >= 1, 0 < --box <= 1, --budgets >= 1 and --limit >= 1 needed")
    budget = max(a.budgets)

    import invphys
    from invphys.core.dataset import DatasetStore
    from invphys.inverter.simulate import masked_score

    inv = invphys.load_inverter(a.bundle)
    overrides = _machine().sim_options(a.sim_option)
    t0 = time.perf_counter()
    answered = []
    for name, path in _sets(a.sets):
        y = DatasetStore(path).arrays(ok_only=True).y[a.first:a.first + a.limit]
        answered.append((name, inv.invert_many(y, method=a.method, top_k=a.starts, seed=a.seed)))
    answer_s = time.perf_counter() - t0
    sim = inv.simulator(overrides)
    ext = inv.extractor(sim)
    searches = build_searches(inv, answered, a.methods, budget, a.q, a.box, a.sigma0, a.seed, a.first)
    head = {"what": "equal-budget refine on the simulator: best R_actual after each budget, per method",
            "device": "", "simulator": sim.name, "simulator_version": sim.version,
            "simulator_config": sim.config.model_dump(), "overrides": overrides, "bundle": a.bundle,
            "answer_method": answered[0][1][0].method if answered and answered[0][1] else a.method,
            "sets": dict(_sets(a.sets)), "first": a.first, "limit": a.limit, "methods": a.methods, "budgets": a.budgets,
            "starts": a.starts, "q": a.q, "box": a.box, "sigma0": a.sigma0, "seed": a.seed,
            "sim_batch": a.sim_batch, "extract_workers": a.extract_workers, "ask_procs": a.ask_procs,
            "answer_s": answer_s}
    clock = {"t0": time.perf_counter()}

    def save(final: bool = False) -> None:
        runs = sum(s.runs for s in searches)
        wall = time.perf_counter() - clock["t0"]
        head["device"] = head["device"] or (_machine().simulator_device(sim) if runs else "")
        result = {**head, "complete": final, "runs": runs, "wall_s": wall, "s_per_run": wall / max(runs, 1),
                  "ask_s": {m: sum(s.ask_s for s in searches if s.key[2] == m) for m in a.methods},
                  "table": table(searches, a.budgets, a.bootstrap)}
        if final:
            _machine().emit(result, a.out)
        elif a.out is not None:
            a.out.parent.mkdir(parents=True, exist_ok=True)
            tmp = a.out.with_suffix(".tmp")
            tmp.write_text(json.dumps({**_machine().provenance(), **result}, indent=1) + "\n")
            tmp.replace(a.out)

    refine_all(sim, ext, searches, masked_score(inv), a.sim_batch, a.extract_workers, a.ask_procs, save)
    save(final=True)
    return 0


def _physical(sim: Any, rows: np.ndarray | None) -> np.ndarray | None:
    if rows is None or len(rows) == 0:
        return None
    return sim.parameter_space().denormalize(np.clip(rows, 0.0, 1.0))


if __name__ == "__main__":
    raise SystemExit(main())
