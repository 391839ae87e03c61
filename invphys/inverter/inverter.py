"""The :class:`Inverter`: a loaded bundle that answers targets with material parameters.

::

    inv = invphys.load_inverter("inverters/orange_peel_paper")
    res = inv.invert({"final_separation": -1.9, ...})          # default: the best amortised policy
    res.parameters                                               # {"E": 812.4, "rho": ..., ...}
    res = inv.invert(target, method="cma_es", top_k=3, refine=200)
    inv.validate(res)                                            # re-run the simulator: R_actual, gap
    inv.polish(res, budget=24)                                   # CMA-ES on the simulator from the answer
"""

from __future__ import annotations

import contextlib
import logging
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError, did_you_mean
from invphys.core.masked_recovery import MaskedRecovery, masked_recovery
from invphys.core.user_targets import UserTargets, from_array, from_mappings
from invphys.inverter.answers import Known, MethodAnswers, Pool, PosteriorAnswers, quiet_cma
from invphys.inverter.bundle import Bundle
from invphys.inverter.diagnosed import failure_score, feature_std, ood_warning, recalibrated
from invphys.inverter.draws import PosteriorDraws
from invphys.inverter.noise import noise_warnings, noisy_rows, posterior_draws
from invphys.inverter.pool import POOL_METHOD, PoolSettings
from invphys.inverter.quiet import quiet
from invphys.inverter.result import Candidate, InversionResult
from invphys.inverter.seeds import check_seed, target_seed
from invphys.inverter.settings import POLISH_SIGMA0, PolishSettings, check_polish
from invphys.inverter.uncertainty import DEFAULT_LEVEL, answer_warnings, check_level

#: candidates closer than this (RMS distance in normalised parameter space) count as one
MIN_DISTANCE = 0.05
REFINE_SIGMA0 = 0.1
#: posterior draws per target kept for its intervals (a method's answer uses its own first draws)
INTERVAL_DRAWS = 256
#: most posterior draws per target
MAX_DRAWS = 100_000
#: batches of at least this many targets run with :func:`blas_threads` (a single target does not pay it)
BLAS_LIMIT_ROWS = 32
_LOG = logging.getLogger("invphys.inverter")
__all__ = ["POLISH_SIGMA0", "Inverter", "PolishSettings", "blas_threads", "check_polish", "load_inverter"]


_CONTROLLER: list[Any] = []


@contextlib.contextmanager
def blas_threads(n: int | None) -> Iterator[None]:
    """Limit BLAS to ``n`` threads (None: leave it). The bundle's networks are small: one thread is
    fastest, and on a busy CPU several threads wait on each other (measured 7x slower on 2 cores)."""
    if n is None:
        yield
        return
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # optional at run time: without it BLAS keeps its default
        yield
        return
    if not _CONTROLLER:
        _CONTROLLER.append(ThreadpoolController())
    with _CONTROLLER[0].limit(limits=n, user_api="blas"):
        yield


def load_inverter(path: str | Path, strict: bool = True, registry: Any = None, threads: int | None = 1) -> Inverter:
    """Load the bundle at ``path`` (checks format, file hashes, simulator version and features).

    ``strict=False`` turns a simulator-version or feature mismatch into a warning
    (:attr:`Inverter.notes`) instead of an error. ``threads``: BLAS threads while inverting, and each answering
    worker's native threads (None: leave).
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        bundle = Bundle(path, registry=registry)
    notes = []
    for w in caught:
        text = str(w.message)
        if not text.startswith("bundle written with Python"):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        elif _python_matters(bundle):
            notes.append(f"{text}: its policy without a NumPy form is loaded through stable-baselines3")
        else:  # every part loads from arrays: the Python version cannot change an answer
            _LOG.debug("%s", text)
    notes += bundle.check_installation(strict=strict)
    return Inverter(bundle, notes, threads=threads)


def _python_matters(bundle: Bundle) -> bool:
    """Whether a part of the bundle is loaded by a library whose saved files depend on the Python
    version (a policy with no NumPy program goes through stable-baselines3)."""
    return any("rollout" in m and not m.get("inference") for m in bundle.methods.values())


class Inverter:
    """Answers targets (features by name) with parameters, through the methods a bundle holds."""

    def __init__(self, bundle: Bundle, notes: Sequence[str] = (), threads: int | None = 1) -> None:
        self.bundle = bundle
        self.notes = list(notes)
        self.threads = threads
        self._runners: dict[str, Any] = {}
        self._plugins: dict[str, Any] = {}
        #: settings of the built-in candidate pool (``method="pool"``); a bundle's pool entry overrides them
        self.pool_settings = PoolSettings()

    # -- description --------------------------------------------------------------------------------
    @property
    def feature_names(self) -> tuple[str, ...]:
        return self.bundle.feature_names

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return self.bundle.space.names

    @property
    def parameter_space(self) -> Any:
        return self.bundle.space

    @property
    def methods(self) -> list[str]:
        """The bundle's methods (trained policies and configured optimisers) by label, and ``pool`` where
        the bundle holds a posterior (:mod:`invphys.inverter.pool`)."""
        extra = [POOL_METHOD] if POOL_METHOD not in self.bundle.methods and self._pool_posterior() else []
        return [*self.bundle.methods, *extra]

    def _pool_posterior(self) -> str | None:
        """The bundle method a built-in pool draws from: the default if it is an NPE, else the first NPE."""
        npe = [k for k, m in self.bundle.methods.items() if m.get("type") == "npe"]
        return self.bundle.default_method if self.bundle.default_method in npe else (npe[0] if npe else None)

    @property
    def default_method(self) -> str:
        m = self.bundle.default_method
        if not m:
            raise InvphysError(f"bundle {self.bundle.root} has no methods; name an optimiser with method=")
        return m

    def __repr__(self) -> str:
        return (f"Inverter({str(self.bundle.root)!r}: {len(self.parameter_names)} parameters, "
                f"{len(self.feature_names)} features, methods {', '.join(self.methods)})")

    # -- targets ------------------------------------------------------------------------------------
    def targets(self, target: Any, partial: bool = False) -> UserTargets:
        """Normalise a target: a mapping, a list of mappings, an array (M,) or (N, M), or UserTargets."""
        if isinstance(target, UserTargets):
            if tuple(target.feature_names) != self.feature_names:
                raise InvphysError("targets were parsed against other features than this bundle's")
            return target
        if isinstance(target, Mapping):
            return from_mappings([target], self.feature_names, partial)
        if isinstance(target, (list, tuple)) and target and all(isinstance(t, Mapping) for t in target):
            return from_mappings(list(target), self.feature_names, partial)
        return from_array(target, self.feature_names)

    def _warnings(self, values: np.ndarray, mask: np.ndarray) -> list[str]:
        b = self.bundle
        out = [(n, v, lo, hi) for n, v, lo, hi, given in zip(self.feature_names, values, b.train_min, b.train_max, mask,
                                                             strict=True) if given and not lo <= v <= hi]
        if not out:
            return []
        text = ", ".join(f"{n} = {v:.4g} (training data {lo:.4g} .. {hi:.4g})" for n, v, lo, hi in out)
        return [f"outside the training data's range, the answer extrapolates: {text}"]

    # -- methods ------------------------------------------------------------------------------------
    def _entry(self, method: str | None) -> tuple[str, dict[str, Any]]:
        label = method or self.default_method
        if label in self.bundle.methods:
            return label, self.bundle.methods[label]
        if label == POOL_METHOD and self._pool_posterior():
            return label, {"type": POOL_METHOD, "kind": "pool", "space": "raw", "evaluator": "shared",
                           "config": {"posterior": self._pool_posterior()}}
        reg = self.bundle.registry
        names = reg.names("optimizer")
        if label in names:
            cls = reg.get("optimizer", label)
            kind = "policy" if getattr(cls, "goal_conditioned", False) else "optimizer"
            return label, {"type": label, "kind": kind, "space": "raw", "evaluator": "shared", "config": {}}
        raise InvphysError(f"unknown method {label!r}.{did_you_mean(label, [*self.methods, *names])} "
                           f"Bundle methods: {', '.join(self.methods) or 'none'}; installed optimisers: "
                           f"{', '.join(names)}")

    def _runner(self, label: str) -> Any:
        from invphys.inverter.policy import PolicyRunner

        if label not in self._runners:
            self._runners[label] = PolicyRunner(self.bundle, label)
        return self._runners[label]

    def _policy_labels(self) -> list[str]:
        return [k for k, m in self.bundle.methods.items() if "rollout" in m]

    def _plugin(self, label: str, entry: dict[str, Any]) -> Any:
        """The optimiser plugin of a method, attached (warm start) or prepared (goal-conditioned)."""
        if label in self._plugins:
            return self._plugins[label]
        from invphys.inverter.policy import PolicyAdapter

        plugin = self.bundle.registry.create("optimizer", {"type": entry["type"], **entry.get("config", {})})
        if hasattr(plugin, "attach") and getattr(plugin, "policy", "x") is None:
            policy = entry.get("config", {}).get("policy")
            pols = self._policy_labels()
            if policy not in pols:
                policy = self.bundle.default_method if self.bundle.default_method in pols else (pols[0] if pols else None)
            if policy is None:
                raise InvphysError(f"method {label!r} needs a trained policy and the bundle has none")
            plugin.attach(PolicyAdapter(self._runner(policy)))
            entry = {**entry, "space": self.bundle.methods[policy]["space"],
                     "evaluator": self.bundle.methods[policy].get("evaluator", "shared")}
        elif getattr(plugin, "goal_conditioned", False) and not getattr(plugin, "prepared", True):
            from invphys.plugins.baselines import learns_from_rows

            if entry.get("path") and hasattr(type(plugin), "load"):
                plugin = self.bundle._plugin_load("optimizer", entry)  # fitted when the bundle was made
            elif learns_from_rows(plugin):
                if hasattr(plugin, "fit_key"):  # a trained estimator (npe): never fitted at answer time
                    raise self.bundle.unfitted_method_error(label, entry["type"])
                theta, y = self.bundle.data("train")
                plugin.fit(theta, y, self.bundle.scales)  # a dataset baseline learns from the training rows
            else:
                trained = ", ".join(self._policy_labels()) or "none"
                raise InvphysError(f"method {label!r} is a goal-conditioned policy that needs training first "
                                   f"(invphys run trains and bundles it); this bundle's trained policies: {trained}")
        self._plugins[label] = (plugin, entry)
        return self._plugins[label]

    def _answers(self, label: str, entry: dict[str, Any]) -> MethodAnswers:
        """The answering object of a method: posterior, lookup, policy or search."""
        from invphys.inverter.answers import LookupAnswers, PolicyAnswers, PosteriorAnswers, SearchAnswers
        from invphys.inverter.draws import has_posterior

        if "rollout" in entry:
            return PolicyAnswers(self, label, entry)
        if entry["type"] == POOL_METHOD:
            return self._pool_answers(label, entry)
        plugin, entry = self._plugin(label, entry)
        if self._is_baseline(entry):
            return (PosteriorAnswers if has_posterior(plugin) else LookupAnswers)(self, label, entry, plugin)
        return SearchAnswers(self, label, entry, plugin)

    def _pool_answers(self, label: str, entry: dict[str, Any]) -> MethodAnswers:
        """The candidate pool: its settings from the entry's config over :attr:`pool_settings`."""
        from invphys.inverter.pool import PoolAnswers

        cfg = dict(entry.get("config") or {})
        base = str(cfg.pop("posterior", None) or self._pool_posterior() or "")
        if base not in self.bundle.methods:
            raise InvphysError(f"method {label!r} needs a posterior method (npe) in the bundle; it has "
                               f"{', '.join(self.bundle.methods) or 'none'}")
        try:
            settings = self.pool_settings.with_(**cfg)
        except TypeError:
            raise InvphysError(f"method {label!r}: unknown pool settings {sorted(cfg)}") from None
        plugin = self._plugin(base, self.bundle.methods[base])[0]
        from invphys.inverter.draws import has_posterior

        if not has_posterior(plugin):
            raise InvphysError(f"method {label!r}: {base!r} holds no posterior to draw from")
        return PoolAnswers(self, label, entry, plugin, base, settings)

    # -- posterior ----------------------------------------------------------------------------------
    def posterior_method(self, method: str | None = None) -> str:
        """The label of a method with a posterior: ``method``, else the default's or the first one's."""
        labels = [method] if method else [self.bundle.default_method or "", *self.methods]
        for label in labels:
            if not label:
                continue
            entry = self._entry(label)[1]
            if entry["type"] == POOL_METHOD:
                return str((entry.get("config") or {}).get("posterior") or self._pool_posterior())
            if "rollout" not in entry and self._is_baseline(entry):
                with quiet():
                    if self._answers(label, entry).kind == "posterior":
                        return label
            if method:
                raise InvphysError(f"method {label!r} has no posterior (it answers with a point)")
        raise InvphysError(f"bundle {self.bundle.root} has no method with a posterior (e.g. npe)")

    def posterior(self, targets: Any, n: int = 1000, seed: int = 0, method: str | None = None,
                  partial: bool = False, recalibrate: bool = True) -> PosteriorDraws:
        """Posterior draws of every target: a :class:`~invphys.inverter.draws.PosteriorDraws` whose
        ``samples`` are (B, n, d) in normalised units ([0, 1]^d, the space's order; physical units:
        ``inv.parameter_space.denormalize``). A target with observation noise (a std per feature) is
        drawn from its noisy posterior under the surrogate (:mod:`~invphys.inverter.noise`). Draws lie
        in the box by rejection (``outside_fraction``),
        each target's from its own stream (seed, method, target), so they do not depend on the batch.
        They are the draws :meth:`invert` uses: corrected by the bundle's stored recalibration (``invphys
        diagnose --write``) unless ``recalibrate`` is False (the posterior's own draws, which ``diagnose``
        measures; the first k of n of those are the same for any n >= k)."""
        seed = check_seed(seed)
        if not is_count(n, 1, MAX_DRAWS):
            raise InvphysError(f"posterior draws must be a whole number in 1 .. {MAX_DRAWS}, got {n!r}")
        t = self.targets(targets, partial)
        label = self.posterior_method(method)
        plugin = self._plugin(label, self._entry(label)[1])[0]
        with quiet(), blas_threads(self.threads if len(t) >= BLAS_LIMIT_ROWS or t.noisy().any() else None):
            draws = posterior_draws(self.bundle, plugin, label, t.values, t.mask, t.std, seed, int(n))[1]
        if recalibrate:  # the recalibration measured the amortised posterior: a noisy target's draws keep theirs
            noisy = noisy_rows(t.std, len(t))
            draws.samples = np.stack([s if z else recalibrated(self.bundle, s)[0]
                                      for s, z in zip(draws.samples, noisy, strict=True)])
        return draws

    # -- inversion ----------------------------------------------------------------------------------
    def invert(self, target: Any, method: str | None = None, top_k: int = 1, refine: int = 0,
               partial: bool = False, seed: int = 0, level: float = DEFAULT_LEVEL,
               draws: int = INTERVAL_DRAWS) -> InversionResult:
        """Answer one target (a feature mapping or an array in the bundle's feature order).

        ``method``: a bundle method or an installed optimiser (default: the best amortised policy);
        ``top_k``: diverse candidates; ``refine``: CMA-ES evaluations spent refining each candidate;
        ``partial``: allow missing features (left out of R); ``seed``: with the target and the method,
        decides every random draw; ``level``: the default level of the result's intervals; ``draws``:
        posterior draws kept for the intervals (methods with a posterior).
        """
        t = self.targets(target, partial)
        if len(t) != 1:
            raise InvphysError(f"invert() takes one target, got {len(t)}: use invert_many()")
        return self.invert_many(t, method=method, top_k=top_k, refine=refine, seed=seed, level=level, draws=draws)[0]

    def invert_many(self, targets: Any, method: str | None = None, top_k: int = 1, refine: int = 0,
                    partial: bool = False, seed: int = 0, level: float = DEFAULT_LEVEL,
                    draws: int = INTERVAL_DRAWS, workers: int = 0,
                    on_answer: Callable[[int], None] | None = None) -> list[InversionResult]:
        """Answer several targets; each answer depends on its target, the method and ``seed`` only (never
        on the other targets or their order). ``workers`` > 1: answered by that many processes, each loading
        the bundle (:mod:`invphys.inverter.parallel`; the same answers, for hundreds of targets).
        ``on_answer(n)``: called as ``n`` more targets are answered (progress bars)."""
        from invphys.inverter.parallel import answer_in_processes, check_workers

        seed, workers = check_seed(seed), check_workers(workers)
        level = check_level(level)
        for name, v, low in (("top_k", top_k, 1), ("refine", refine, 0), ("draws", draws, 1)):
            if not is_count(v, low):
                raise InvphysError(f"{name} must be a whole number >= {low}, got {v!r}")
        if draws > MAX_DRAWS:
            raise InvphysError(f"draws must be at most {MAX_DRAWS} per target, got {draws}")
        t = self.targets(targets, partial)
        label, entry = self._entry(method)
        if workers > 1 and len(t) > 1:
            return answer_in_processes(self, t, workers, {"method": method, "top_k": top_k, "refine": refine,
                                                           "seed": seed, "level": level, "draws": draws},
                                       load_inverter, on_answer)
        with quiet(), blas_threads(self.threads if len(t) >= BLAS_LIMIT_ROWS or t.noisy().any() else None):
            answers = self._answers(label, entry)
            answers.check_top_k(top_k)
            if t.std is not None and isinstance(answers, PosteriorAnswers):
                answers.noise = t.std
            out, t0 = [], time.perf_counter()
            for i, ans in enumerate(answers.answer_all(t.values, t.mask, top_k, seed, draws)):
                out.append(self._answer_one(answers, ans, t, i, refine, seed, level, top_k, t0))
                t0 = time.perf_counter()
                if on_answer is not None:
                    on_answer(1)
            return out

    def _answer_one(self, answers: MethodAnswers, ans: tuple[Pool, Any], t: UserTargets, i: int, refine: int,
                    seed: int, level: float, top_k: int, t0: float) -> InversionResult:
        """The result of target ``i`` from its method's pool ``ans``; ``t0``: when its answer began (work
        shared across targets counts towards the target that waited for it)."""
        values, mask = t.values[i], t.mask[i]
        std = None if t.std is None else t.std[i]
        noisy = bool(noisy_rows(None if std is None else std[None, :], 1)[0])
        pool, unc = ans
        spent = pool.spent
        unc.level = level
        if unc.kind == "posterior" and unc.has_draws and not noisy:
            unc.draws, unc.recalibrated = recalibrated(self.bundle, unc.draws)
        ranked = bool(getattr(getattr(answers, "settings", None), "exact", False))  # a pool scoring rows exactly
        cands = self._select(pool, values, mask, top_k, float(getattr(answers, "lam", 0.0)), ranked)
        if refine:
            cands, extra = self._refine(cands, values, mask, refine, target_seed(seed, answers.label, values, mask,
                                                                                  "refine"))
            spent += extra
        self._calibrate_error_bars(cands)
        fail_p = failure_score(self.bundle, values, mask, cands[0].theta)
        warn = (self._warnings(values, mask) + ood_warning(self.bundle, values, mask, cands[0].theta, fail_p)
                + answer_warnings(unc, self.parameter_names, cands[0].theta, mask) + noise_warnings(noisy, unc.kind))
        return InversionResult(
            label=t.labels[i], method=answers.label, target=values, mask=mask, candidates=cands,
            parameter_names=self.parameter_names, parameter_units=tuple(p.unit for p in self.bundle.space.parameters),
            feature_names=self.feature_names, feature_units=self.bundle.feature_units, evaluations=spent,
            wall_time_s=time.perf_counter() - t0, warnings=warn,
            failure_score=fail_p,
            bundle_id=str(self.bundle.manifest.get("bundle_id", "")), parameter_uncertainty=unc, space=self.bundle.space,
            target_std=std, noise_posterior=noisy and unc.kind == "posterior")

    def invert_array(self, values: np.ndarray, method: str | None = None) -> np.ndarray:
        """The fast path: normalised parameters (N, d) for complete targets (N, M) by a bundle policy or
        a dataset baseline without a posterior, in one batched answer. Batching changes float rounding,
        so an answer may differ from :meth:`invert`'s in its last bits; a posterior method (and the pool)
        is answered exactly as :meth:`invert` answers it (draws made together, each from its own stream)."""
        label, entry = self._entry(method)
        t = from_array(values, self.feature_names)
        if entry["type"] == POOL_METHOD:  # draws per target from its own stream, as invert answers
            return np.array([r.theta for r in self.invert_many(t, method=label, draws=1)])
        if "rollout" not in entry and self._is_baseline(entry):
            with quiet(), blas_threads(self.threads if len(t) >= BLAS_LIMIT_ROWS else None):
                answers = self._answers(label, entry)
                if answers.kind == "posterior":
                    return np.array([r.theta for r in self.invert_many(t, method=label, draws=1)])
                sur = self.bundle.surrogate
                from invphys.plugins.baselines import answer_with_penalty

                return answer_with_penalty(answers.plugin, t.values, sur.predict, sur, self.bundle.scales,  # type: ignore[attr-defined]
                                           f"method {label!r}").theta
        if "rollout" not in entry:
            raise InvphysError(f"invert_array needs a trained policy; {label!r} is a {entry['type']} optimiser")
        runner = self._runner(label)
        with blas_threads(self.threads if len(t) >= BLAS_LIMIT_ROWS else None):
            points, _, _ = runner.rollout(t.values).best()
            return np.clip(runner.space.to_theta(points), 0.0, 1.0)

    def _is_baseline(self, entry: dict[str, Any]) -> bool:
        from invphys.plugins.baselines import learns_from_rows

        return learns_from_rows(self.bundle.registry.get("optimizer", entry["type"]))

    # -- candidates ---------------------------------------------------------------------------------
    def _calibrate_error_bars(self, cands: list[Candidate]) -> list[Candidate]:
        """The error bars an answer shows: the ensemble's std, calibrated where the bundle holds diagnostics
        (after choosing, which keeps the ensemble's own spread)."""
        if cands:
            for c, std in zip(cands, feature_std(self.bundle, np.array([c.std for c in cands])), strict=True):
                c.std = std
        return cands

    def _candidates(self, thetas: np.ndarray, sources: list[str], target: np.ndarray, mask: np.ndarray,
                    known: Sequence[Known | None] | None = None) -> list[Candidate]:
        """Candidates at ``thetas`` scored by the surrogate; ``known``: row for row, the stored row a theta
        is (its real features and their R become the candidate's ``known`` and ``r_known``)."""
        thetas = np.clip(np.atleast_2d(thetas), 0.0, 1.0)
        mean, std = self.bundle.surrogate.predict_with_uncertainty(thetas)
        r = masked_recovery(mean, target, self.bundle.scales, mask, self.bundle.kappa)
        params = self.bundle.space.denormalize(thetas)
        rows: list[Known | None] = [None] * len(thetas) if known is None else list(known)
        return [Candidate(theta=thetas[j], params=params[j], predicted=mean[j], std=std[j], r_surrogate=float(r[j]),
                          source=sources[j], known=None if k is None else np.asarray(k.features, dtype=np.float64),
                          r_known=None if k is None else float(k.r)) for j, k in enumerate(rows)]

    def _select(self, pool: Pool, target: np.ndarray, mask: np.ndarray, k: int, lam: float = 0.0,
                ranked: bool = False) -> list[Candidate]:
        """The best ``k`` candidates that are at least :data:`MIN_DISTANCE` apart (best: highest R_surr,
        minus ``lam`` x the normalised ensemble std where a method scores so; ``ranked``: the method's own
        order, e.g. a pool that scores stored rows by their real features)."""
        from invphys.evaluators.uncertainty import normalised_std

        cands = self._candidates(pool.thetas, pool.sources, target, mask, pool.known)
        if not ranked:
            pen = lam * normalised_std(np.array([c.std for c in cands]), self.bundle.scales) if lam else 0.0
            order = np.lexsort((np.arange(len(cands)), -(np.array([c.r_surrogate for c in cands]) - pen)))
            cands = [cands[i] for i in order]
        if k == 1:
            return cands[:1]
        chosen: list[Candidate] = []
        d = len(cands[0].theta)
        for c in cands:
            if all(np.linalg.norm(c.theta - o.theta) / np.sqrt(d) >= MIN_DISTANCE for o in chosen):
                chosen.append(c)
                if len(chosen) == k:
                    break
        return chosen

    def _refine(self, cands: list[Candidate], target: np.ndarray, mask: np.ndarray, budget: int, seed: int
                ) -> tuple[list[Candidate], int]:
        """Warm-started CMA-ES (sigma0 0.1 in [0, 1]^d) from each candidate; keeps the better point."""
        from invphys.core.spaces import build_problem, raw_space
        from invphys.plugins.optimizers.cma_es import CMAES

        objective = MaskedRecovery(np.where(mask, target, 0.0), self.bundle.scales, mask, self.bundle.kappa)
        out, spent = [], 0
        for j, c in enumerate(cands):
            problem = build_problem(raw_space(len(c.theta)), objective, budget, predict=self.bundle.surrogate.predict,
                                    initial=c.theta, seed=seed * 100 + j)
            with quiet_cma():
                res = CMAES(sigma0=REFINE_SIGMA0, popsize=min(20, max(2, budget // 2)), budget=budget).optimize(problem)
            spent += int(res.evaluations)
            new = self._candidates(np.asarray(res.theta)[None, :], [f"{c.source} + refine({budget})"], target, mask)[0]
            out.append(new if new.r_surrogate > c.r_surrogate else c)
        out.sort(key=lambda c: -c.r_surrogate)
        return out, spent

    def evaluate(self, parameters: Any = None, target: Any = None, partial: bool = False, label: str = "given",
                 theta: Any = None) -> InversionResult:
        """An :class:`InversionResult` for given parameters (a ``{name: value}`` mapping or a physical
        vector; or normalised ``theta``: one vector, or one row per candidate) against a target, e.g. to
        validate known parameters or to refine starts answered elsewhere."""
        if target is None or (parameters is None) == (theta is None):
            raise InvphysError("evaluate() needs a target and either parameters or theta")
        t = self.targets(target, partial)
        space = self.bundle.space
        if theta is not None:
            theta = space.check_unit(np.atleast_2d(np.asarray(theta, dtype=np.float64)))
            if theta.ndim != 2:
                raise InvphysError(f"theta: one vector or one row per candidate, got shape {theta.shape}")
        else:
            phys = space.from_mapping(parameters) if isinstance(parameters, Mapping) else space.check(parameters)
            theta = space.normalize(phys).reshape(1, -1)
        cands = self._calibrate_error_bars(self._candidates(theta, [label] * len(theta), t.values[0], t.mask[0]))
        return InversionResult(label=t.labels[0], method=label, target=t.values[0], mask=t.mask[0], candidates=cands,
                               parameter_names=self.parameter_names,
                               parameter_units=tuple(p.unit for p in space.parameters),
                               feature_names=self.feature_names, feature_units=self.bundle.feature_units,
                               warnings=self._warnings(t.values[0], t.mask[0]),
                               bundle_id=str(self.bundle.manifest.get("bundle_id", "")),
                               target_std=None if t.std is None else t.std[0])

    # -- validation ---------------------------------------------------------------------------------
    def simulator(self, overrides: Mapping[str, Any] | None = None) -> Any:
        """The bundle's simulator (its recorded config, with ``overrides``), from the installed plugin."""
        block = {**self.bundle.manifest["simulator"]["config"], **dict(overrides or {})}
        try:
            return self.bundle.registry.create("simulator", block)
        except InvphysError:
            raise
        except Exception as exc:  # pydantic validation of overrides
            raise InvphysError(f"simulator options do not fit {block.get('type')!r}: "
                               f"{str(exc).splitlines()[0]}") from None

    def extractor(self, simulator: Any = None) -> Any:
        block = self.bundle.manifest["features"].get("extractor") or {}
        if not block.get("type"):
            name = simulator.default_feature_extractor() if simulator is not None else None
            if not name:
                raise InvphysError("the bundle names no feature extractor")
            block = {"type": name}
        return self.bundle.registry.create("feature_extractor", block)

    # -- validation ---------------------------------------------------------------------------------
    def validate(self, results: InversionResult | Sequence[InversionResult], overrides: Mapping[str, Any] | None = None,
                 batch_size: int = 16, on_run: Callable[[int], None] | None = None, extract_workers: int = 0
                 ) -> InversionResult | list[InversionResult]:
        """Re-run every candidate through the simulator: fills ``actual``, ``r_actual`` and ``gap``.

        ``overrides`` change the recorded simulator config (e.g. ``{"arch": "cpu"}``); ``on_run(i)`` is
        called as each run finishes. ``batch_size``: runs in flight (a simulator with a continuous-batching
        stream, e.g. the AnisoMPM foods on a GPU, runs every candidate in one stream, as dataset generation
        does; others take chunks of it); ``extract_workers``: feature-extraction processes while the simulator
        goes on (0: in its thread). Returns ``results`` (updated in place).
        """
        from invphys.inverter.simulate import simulate, simulation

        items: list[InversionResult] = [results] if isinstance(results, InversionResult) else list(results)
        simulate(self, [(r, c) for r in items for c in r.candidates],
                 *simulation(self, overrides, batch_size, extract_workers), on_run=on_run)
        return items[0] if isinstance(results, InversionResult) else items

    # -- simulator-in-the-loop polish -------------------------------------------------------------------
    def polish(self, results: InversionResult | Sequence[InversionResult], budget: int = 24, popsize: int = 8,
               sigma0: float = POLISH_SIGMA0, below: float = 1.0, overrides: Mapping[str, Any] | None = None,
               batch_size: int = 16, log: str | Path | None = None, seed: int = 0,
               on_batch: Callable[[int, bool], None] | None = None, confirm: int = 0,
               confirm_candidates: int = 4, settings: PolishSettings | None = None
               ) -> InversionResult | list[InversionResult]:
        """Ask/tell CMA-ES on the real simulator from each result's best simulated candidate.

        Candidates not validated yet are validated first. A result whose best R_actual is below
        ``below`` gets ``budget`` new simulator runs (``popsize`` points per generation, step ``sigma0``
        in [0, 1]^d; every generation of all results is simulated as one batch, in chunks of
        ``batch_size``). A better simulated point becomes a new first candidate (source
        ``"<start> + polish"``); otherwise the start moves first: the answer is never worse. Partial
        targets are scored over their given features, as :meth:`validate` scores them. ``log``: an
        ``.npz`` file of every simulated batch, so that a stopped polish resumes (a re-run replays the
        logged batches; a larger ``budget`` replays the smaller one's); it is checked before anything
        is simulated. ``on_batch(runs, replayed)`` follows each batch. Fills ``result.polish``; returns
        ``results`` (updated in place). ``settings``: a :class:`PolishSettings` instead of the keywords.

        ``confirm`` K > 0: afterwards, every result's best ``confirm_candidates`` simulated points (its
        polish's answer and the next best points its polish simulated; a result that was not polished:
        its answer alone) are simulated K more times, all in one batch through the same log, and the
        candidate with the best mean R over those K runs becomes the first candidate, with that mean as
        its ``r_actual`` (its ``actual`` stays the features of the run that found it; other candidates
        keep their single-run R). ``result.polish["confirm"]`` records ``r_selected`` (best of N),
        ``r_confirmed``, every run's R and whether the answer changed
        (:func:`~invphys.evaluators.polish.confirm`). Cost: K x candidates runs per result.
        """
        from invphys.inverter.simulate import polish

        ps = settings or PolishSettings.checked(budget=budget, popsize=popsize, sigma0=sigma0, below=below,
                                                confirm=confirm, confirm_candidates=confirm_candidates)
        items: list[InversionResult] = [results] if isinstance(results, InversionResult) else list(results)
        polish(self, items, ps, overrides, batch_size, log, check_seed(seed), on_batch)
        return items[0] if isinstance(results, InversionResult) else items
