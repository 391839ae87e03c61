"""Optuna's samplers (TPE, CMA-ES, Gaussian process, random) as an optimiser plugin, with Optuna storages.

Optuna is optional (``pip install 'invphys[optuna]'``) and imported inside :meth:`OptunaOptimizer.optimize`.
"""

from __future__ import annotations

import hashlib
import warnings
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig, Problem
from invphys.core.results import OptimizationResult
from invphys.plugins.optimizers._base import BudgetExhausted, BuiltinOptimizer, Tracker

EXTRA_HINT = "pip install 'invphys[optuna]'"
#: the study attribute that marks a study as written by invphys (only those are replaced)
MARK = "invphys"
SQLITE_SUFFIXES = (".db", ".sqlite", ".sqlite3")


class OptunaOptimizer(BuiltinOptimizer):
    """An Optuna sampler over the space's box, asked ``batch_size`` trials at a time (ask/tell).

    ``sampler``: ``tpe`` (Tree-structured Parzen Estimator, multivariate, constant liar for batches),
    ``cmaes`` (CMA-ES through the ``cmaes`` package), ``gp`` (Gaussian-process Bayesian optimisation; each
    ask fits a GP, so keep its budget in the hundreds) or ``random``. Each round's trials are evaluated in
    one surrogate call and told back; the total never exceeds ``min(budget, problem.budget)``. Seeded by
    ``seed`` or, by default, the problem's seed (every target has its own): the same problem gives the same
    answer. ``problem.initial`` (a warm start) is the first trial.

    ``storage`` (an Optuna storage: an ``sqlite:///...`` or other database URL, or a file path: ``*.db`` is
    SQLite, anything else a journal file) keeps every study for Optuna's own tools (``optuna-dashboard``); the
    default keeps them in memory. Each problem is a study named ``{study_name}-{seed}-{target digest}``; a
    study of that name that invphys wrote before is replaced, any other is an error.
    """

    name: ClassVar[str] = "optuna"

    class Config(PluginConfig):
        sampler: Literal["tpe", "cmaes", "gp", "random"] = Field("tpe", description="the Optuna sampler")
        budget: int = Field(500, ge=1, description="surrogate evaluations (trials) per optimisation")
        batch_size: int = Field(20, ge=1, description="trials asked (and evaluated together) per round")
        seed: int | None = Field(None, description="random seed (default: the problem's seed)")
        sampler_options: dict[str, Any] = Field(
            default_factory=dict, description="keyword arguments of the sampler's constructor "
                                              "(e.g. n_startup_trials, sigma0, popsize); not seed")
        storage: str | None = Field(None, description="Optuna storage URL or file path (default: in memory)")
        study_name: str = Field("invphys", min_length=1, description="prefix of each problem's study name")

    def optimize(self, problem: Problem) -> OptimizationResult:
        optuna = _import_optuna()
        cfg = self.config
        seed = int(problem.seed if cfg.seed is None else cfg.seed)
        space = problem.space
        keys = [f"x{i}" for i in range(space.dim)]
        dists = {k: optuna.distributions.FloatDistribution(float(space.low), float(space.high)) for k in keys}
        storage = _storage(optuna, cfg.storage)
        study_name = f"{cfg.study_name}-{seed}-{_digest(problem)}"
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            if storage is not None:
                _replace_own_study(optuna, storage, study_name)
            study = optuna.create_study(direction="maximize", sampler=self._sampler(optuna, seed),
                                        storage=storage, study_name=study_name if storage is not None else None)
            study.set_user_attr(MARK, True)
            if problem.initial is not None:
                x0 = np.clip(np.asarray(problem.initial, dtype=np.float64).reshape(-1), space.low, space.high)
                study.enqueue_trial(dict(zip(keys, x0.tolist(), strict=True)))
            tracker = Tracker(problem, cfg.budget)
            try:
                while tracker.remaining > 0:
                    trials = [study.ask(dists) for _ in range(min(cfg.batch_size, tracker.remaining))]
                    points = np.array([[t.params[k] for k in keys] for t in trials], dtype=np.float64)
                    scores = tracker.evaluate(points)
                    for trial, score in zip(trials, scores, strict=True):
                        if np.isfinite(score):
                            study.tell(trial, float(score))
                        else:
                            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            except BudgetExhausted:
                pass
        return tracker.result(sampler=cfg.sampler, study=study_name if storage is not None else None)

    def _sampler(self, optuna: Any, seed: int) -> Any:
        cfg = self.config
        options = dict(cfg.sampler_options)
        if "seed" in options:
            raise InvphysError("optuna: set the seed with 'seed', not in sampler_options")
        samplers = {"tpe": optuna.samplers.TPESampler, "cmaes": optuna.samplers.CmaEsSampler,
                    "gp": optuna.samplers.GPSampler, "random": optuna.samplers.RandomSampler}
        if cfg.sampler == "tpe":
            options.setdefault("multivariate", True)
        if cfg.sampler == "cmaes":
            _need("cmaes", "the cmaes sampler")
        if cfg.sampler == "gp":
            _need("scipy", "the gp sampler")
            _need("torch", "the gp sampler")
        try:
            return samplers[cfg.sampler](seed=seed % (2**32), **options)
        except TypeError as exc:
            raise InvphysError(f"optuna: sampler_options do not fit the {cfg.sampler} sampler: {exc}") from None


def _import_optuna() -> Any:
    try:
        import optuna
    except ImportError:
        raise InvphysError(f"the optuna optimiser needs Optuna: {EXTRA_HINT}") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


def _need(module: str, what: str) -> None:
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise InvphysError(f"optuna: {what} needs the {module} package: {EXTRA_HINT}")


def _storage(optuna: Any, storage: str | None) -> Any:
    """None (in memory), a database URL as given, or a file path: SQLite for ``*.db``, else a journal file."""
    if storage is None:
        return None
    if "://" in storage:
        return storage
    path = Path(storage).expanduser().resolve()
    if path.is_dir():
        raise InvphysError(f"optuna storage {storage!r} is a directory: name a file (e.g. optuna.db)")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix in SQLITE_SUFFIXES:
        return f"sqlite:///{path}"
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    return JournalStorage(JournalFileBackend(str(path)))


def _replace_own_study(optuna: Any, storage: Any, name: str) -> None:
    """Delete a study named ``name`` that invphys wrote (a re-run of the same problem); refuse any other."""
    try:
        old = optuna.load_study(study_name=name, storage=storage)
    except KeyError:
        return
    if not old.user_attrs.get(MARK):
        raise InvphysError(f"optuna storage already holds a study {name!r} that invphys did not write: "
                           f"choose another study_name or storage")
    optuna.delete_study(study_name=name, storage=storage)


def _digest(problem: Problem) -> str:
    """8 hex digits of the problem's target (the objective's name when it has none)."""
    if problem.target is not None:
        blob = np.ascontiguousarray(np.asarray(problem.target, dtype=np.float64)).tobytes()
    else:
        blob = str(getattr(problem.objective, "name", "") or problem.info.get("label", "")).encode()
    return hashlib.sha256(blob).hexdigest()[:8]
