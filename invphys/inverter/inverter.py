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

from invphys.core.errors import InvphysError, did_you_mean
from invphys.core.user_targets import UserTargets, from_array, from_mappings
from invphys.inverter.bundle import Bundle
from invphys.inverter.objective import MaskedRecovery, masked_recovery
from invphys.inverter.result import Candidate, InversionResult

#: candidates closer than this (RMS distance in normalised parameter space) count as one
MIN_DISTANCE = 0.05
REFINE_SIGMA0 = 0.1
#: polish's CMA-ES step in [0, 1]^d: the simulator is sharp in its parameters (orange peel, paper
#: preset: sigma0 0.05 improved 13 of 62 targets in its first generation; 0.012 improved 31 of 35 in
#: three generations, none got worse; results/orange_peel_paper_active_polish)
POLISH_SIGMA0 = 0.012
#: batches of at least this many targets run with :func:`blas_threads` (a single target does not pay it)
BLAS_LIMIT_ROWS = 32
_LOG = logging.getLogger("invphys.inverter")
#: candidate thetas (P, d), their sources, evaluations spent
Pool = tuple[np.ndarray, list[str], int]


@contextlib.contextmanager
def _quiet_cma() -> Iterator[None]:
    """Silence cma's warning about an injected start point (a warm start injects one on purpose)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="orphanated injected solution")
        yield


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
    (:attr:`Inverter.notes`) instead of an error. ``threads``: BLAS threads while inverting (None: leave).
    """
    bundle = Bundle(path, registry=registry)
    notes = bundle.check_installation(strict=strict)
    return Inverter(bundle, notes, threads=threads)


class Inverter:
    """Answers targets (features by name) with parameters, through the methods a bundle holds."""

    def __init__(self, bundle: Bundle, notes: Sequence[str] = (), threads: int | None = 1) -> None:
        self.bundle = bundle
        self.notes = list(notes)
        self.threads = threads
        self._runners: dict[str, Any] = {}
        self._plugins: dict[str, Any] = {}

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
        """The bundle's methods (trained policies and configured optimisers) by label."""
        return list(self.bundle.methods)

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
                theta, y = self.bundle.data("train")
                plugin.fit(theta, y, self.bundle.scales)  # a dataset baseline learns from the training rows
            else:
                trained = ", ".join(self._policy_labels()) or "none"
                raise InvphysError(f"method {label!r} is a goal-conditioned policy that needs training first "
                                   f"(invphys run trains and bundles it); this bundle's trained policies: {trained}")
        self._plugins[label] = (plugin, entry)
        return self._plugins[label]

    # -- posterior ----------------------------------------------------------------------------------
    def posterior_method(self, method: str | None = None) -> str:
        """The label of a method with a posterior: ``method``, else the default's or the first one's."""
        from invphys.inverter.draws import has_posterior

        labels = [method] if method else [self.bundle.default_method or "", *self.methods]
        for label in labels:
            if not label:
                continue
            entry = self._entry(label)[1]
            if self._is_baseline(entry) and has_posterior(self._plugin(label, entry)[0]):
                return label
            if method:
                raise InvphysError(f"method {label!r} has no posterior (it answers with a point)")
        raise InvphysError(f"bundle {self.bundle.root} has no method with a posterior (e.g. npe)")

    def posterior(self, targets: Any, n: int = 1000, seed: int = 0, method: str | None = None,
                  partial: bool = False) -> Any:
        """Posterior draws of every target: a :class:`~invphys.inverter.draws.PosteriorDraws` whose
        ``samples`` are (B, n, d) in normalised units ([0, 1]^d, the space's order; physical units:
        ``inv.parameter_space.denormalize``). Draws lie in the box by rejection (``outside_fraction``),
        each target's from its own stream (seed, method, target), so they do not depend on the batch."""
        from invphys.inverter.draws import completions, sample_posterior
        from invphys.inverter.seeds import check_seed, target_seed

        seed = check_seed(seed)
        t = self.targets(targets, partial)
        label = self.posterior_method(method)
        plugin = self._plugin(label, self._entry(label)[1])[0]
        mean = np.asarray(self.bundle.manifest["features"]["mean"], dtype=np.float64)
        train_y = None if t.mask.all() else self.bundle.data("train")[1]
        conds = [completions(t.values[i], t.mask[i], train_y, mean, self.bundle.scales) for i in range(len(t))]
        seeds = [target_seed(seed, label, t.values[i], t.mask[i], "posterior") for i in range(len(t))]
        return sample_posterior(plugin, conds, seeds, int(n))

    # -- inversion ----------------------------------------------------------------------------------
    def invert(self, target: Any, method: str | None = None, top_k: int = 1, refine: int = 0,
               partial: bool = False, seed: int = 0) -> InversionResult:
        """Answer one target (a feature mapping or an array in the bundle's feature order).

        ``method``: a bundle method or an installed optimiser (default: the best amortised policy);
        ``top_k``: diverse candidates; ``refine``: CMA-ES evaluations spent refining each candidate;
        ``partial``: allow missing features (left out of R).
        """
        t = self.targets(target, partial)
        if len(t) != 1:
            raise InvphysError(f"invert() takes one target, got {len(t)}: use invert_many()")
        return self.invert_many(t, method=method, top_k=top_k, refine=refine, seed=seed)[0]

    def invert_many(self, targets: Any, method: str | None = None, top_k: int = 1, refine: int = 0,
                    partial: bool = False, seed: int = 0) -> list[InversionResult]:
        """Answer several targets (a policy answers them all in one batched rollout)."""
        if top_k < 1:
            raise InvphysError(f"top_k must be >= 1, got {top_k}")
        if refine < 0:
            raise InvphysError(f"refine must be >= 0 evaluations, got {refine}")
        t = self.targets(targets, partial)
        label, entry = self._entry(method)
        with blas_threads(self.threads if len(t) >= BLAS_LIMIT_ROWS else None):
            return self._invert(t, label, entry, top_k, refine, seed)

    def _invert(self, t: UserTargets, label: str, entry: dict[str, Any], top_k: int, refine: int,
                seed: int) -> list[InversionResult]:
        t0 = time.perf_counter()
        if "rollout" in entry:
            pools = self._policy_pools(label, t, top_k, seed)
        elif self._is_baseline(entry):
            pools = self._baseline_pools(label, entry, t, top_k)
        else:
            pools = self._optimizer_pools(label, entry, t, top_k, seed)
        elapsed = (time.perf_counter() - t0) / len(t)
        results = []
        for i in range(len(t)):
            t1 = time.perf_counter()
            thetas, sources, spent = pools[i]
            cands = self._select(thetas, sources, t.values[i], t.mask[i], top_k)
            if refine:
                cands, extra = self._refine(cands, t.values[i], t.mask[i], refine, seed + i)
                spent += extra
            results.append(InversionResult(
                label=t.labels[i], method=label, target=t.values[i], mask=t.mask[i], candidates=cands,
                parameter_names=self.parameter_names, parameter_units=tuple(p.unit for p in self.bundle.space.parameters),
                feature_names=self.feature_names, feature_units=self.bundle.feature_units, evaluations=spent,
                wall_time_s=elapsed + time.perf_counter() - t1, warnings=self._warnings(t.values[i], t.mask[i]),
                bundle_id=str(self.bundle.manifest.get("bundle_id", ""))))
        return results

    def invert_array(self, values: np.ndarray, method: str | None = None) -> np.ndarray:
        """The fast path: normalised parameters (N, d) for complete targets (N, M) by a bundle policy or
        dataset baseline (one batched answer)."""
        label, entry = self._entry(method)
        if "rollout" not in entry and self._is_baseline(entry):  # a policy answers without torch
            t = from_array(values, self.feature_names)
            with blas_threads(self.threads if len(t) >= BLAS_LIMIT_ROWS else None):
                return self._baseline_answers(label, entry, t.values).theta
        if "rollout" not in entry:
            raise InvphysError(f"invert_array needs a trained policy; {label!r} is a {entry['type']} optimiser")
        t = from_array(values, self.feature_names)
        runner = self._runner(label)
        with blas_threads(self.threads if len(t) >= BLAS_LIMIT_ROWS else None):
            points, _, _ = runner.rollout(t.values).best()
            return np.clip(runner.space.to_theta(points), 0.0, 1.0)

    def _policy_pools(self, label: str, t: UserTargets, top_k: int, seed: int) -> list[Pool]:
        """Per target: the visited states of the policy's rollouts (and, for top_k > 1, of the bundle's
        other policies) as candidate thetas, their sources and the evaluations spent."""
        runner = self._runner(label)
        goals = np.where(t.mask, t.values, np.asarray(runner.mean)[None, :])
        if top_k == 1:
            points, _, _ = runner.rollout(goals, t.mask, seed=seed).best()
            theta = runner.space.to_theta(points)
            return [(theta[i:i + 1], [label], runner.horizon) for i in range(len(t))]
        rollouts = max(8, 4 * top_k)
        ro = runner.rollout(goals, t.mask, rollouts=rollouts, seed=seed)
        n = len(t)
        theta = runner.space.to_theta(ro.points.reshape(-1, runner.dim)).reshape(n, -1, self.bundle.space.dim)
        srcs = [f"{label} (rollout {r + 1})" for r in range(rollouts) for _ in range(runner.horizon)]
        pools = [(theta[i], list(srcs), rollouts * runner.horizon) for i in range(n)]
        for other in self._policy_labels():
            if other == label:
                continue
            r2 = self._runner(other)
            pts = r2.rollout(np.where(t.mask, t.values, r2.mean[None, :]), t.mask, seed=seed).points
            th = r2.space.to_theta(pts.reshape(-1, r2.dim)).reshape(n, -1, self.bundle.space.dim)
            for i in range(n):
                pools[i] = (np.concatenate([pools[i][0], th[i]]), pools[i][1] + [other] * th.shape[1],
                            pools[i][2] + r2.horizon)
        return pools

    def _is_baseline(self, entry: dict[str, Any]) -> bool:
        from invphys.plugins.baselines import learns_from_rows

        return learns_from_rows(self.bundle.registry.get("optimizer", entry["type"]))

    def _baseline_answers(self, label: str, entry: dict[str, Any], goals: np.ndarray) -> Any:
        """A dataset baseline's answers for all ``goals`` (B, M) in one batch (its seeded draws are
        then the same whichever path asks), choosing among candidates on the bundle's surrogate."""
        from invphys.plugins.baselines import answer_with_penalty

        plugin, _ = self._plugin(label, entry)
        sur = self.bundle.surrogate
        return answer_with_penalty(plugin, np.asarray(goals, dtype=np.float64), sur.predict, sur, self.bundle.scales,
                                   f"method {label!r}")

    def _baseline_pools(self, label: str, entry: dict[str, Any], t: UserTargets, top_k: int) -> list[Pool]:
        """Per target: a dataset baseline's answer, or with it all its candidates (posterior draws) for
        top_k > 1 and for a partial target, whose missing features the baseline saw as the training
        mean: the candidates are then chosen by R over the given features only."""
        m = self.bundle.manifest["features"]
        ans = self._baseline_answers(label, entry, np.where(t.mask, t.values, np.asarray(m["mean"])[None, :]))
        spent = ans.evaluations + 1  # as DatasetBaseline.optimize counts: the candidates and the answer
        pools: list[Pool] = []
        for i in range(len(t)):
            if top_k == 1 and t.mask[i].all():
                pools.append((ans.theta[i:i + 1], [label], int(spent[i])))
            else:
                k = ans.candidates.shape[1]
                pools.append((np.concatenate([ans.theta[i:i + 1], ans.candidates[i]]), [label] * (k + 1),
                              int(spent[i])))
        return pools

    def _optimizer_pools(self, label: str, entry: dict[str, Any], t: UserTargets, top_k: int, seed: int
                         ) -> list[Pool]:
        """Per target: the answers of ``top_k`` runs of an optimiser (different seeds)."""
        from invphys.core.spaces import build_problem

        plugin, entry = self._plugin(label, entry)
        space = self.bundle.search_space(entry["space"])
        predict = self.bundle.predictor(entry["space"], entry.get("evaluator", "shared"))
        latent = None if entry["space"] == "raw" else self.bundle.latent(entry["space"])
        budget = int(getattr(plugin, "evaluation_budget", 0) or getattr(plugin.config, "budget", 0) or 5000)
        m = self.bundle.manifest["features"]
        mean, std = np.asarray(m["mean"]), np.asarray(m["std"])
        pools: list[Pool] = []
        for i in range(len(t)):
            goal = np.where(t.mask[i], t.values[i], mean)
            objective = MaskedRecovery(goal, self.bundle.scales, t.mask[i], self.bundle.kappa)
            thetas, srcs, spent = [], [], 0
            for r in range(top_k):
                problem = build_problem(space, objective, budget, surrogate=self.bundle.surrogate,
                                        latent=latent,
                                        predict=predict, target=goal, seed=seed + 1000 * r + i,
                                        feature_mean=mean, feature_std=std)
                with _quiet_cma():
                    res = plugin.optimize(problem)
                thetas.append(np.clip(np.asarray(res.theta, dtype=np.float64), 0.0, 1.0))
                srcs.append(label if top_k == 1 else f"{label} (seed {seed + 1000 * r + i})")
                spent += int(res.evaluations)
            pools.append((np.array(thetas), srcs, spent))
        return pools

    # -- candidates ---------------------------------------------------------------------------------
    def _candidates(self, thetas: np.ndarray, sources: list[str], target: np.ndarray, mask: np.ndarray
                    ) -> list[Candidate]:
        thetas = np.clip(np.atleast_2d(thetas), 0.0, 1.0)
        mean, std = self.bundle.surrogate.predict_with_uncertainty(thetas)
        r = masked_recovery(mean, target, self.bundle.scales, mask, self.bundle.kappa)
        params = self.bundle.space.denormalize(thetas)
        return [Candidate(theta=thetas[j], params=params[j], predicted=mean[j], std=std[j], r_surrogate=float(r[j]),
                          source=sources[j]) for j in range(len(thetas))]

    def _select(self, thetas: np.ndarray, sources: list[str], target: np.ndarray, mask: np.ndarray,
                k: int) -> list[Candidate]:
        """The best ``k`` candidates that are at least :data:`MIN_DISTANCE` apart."""
        cands = sorted(self._candidates(thetas, sources, target, mask), key=lambda c: -c.r_surrogate)
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
            with _quiet_cma():
                res = CMAES(sigma0=REFINE_SIGMA0, popsize=min(20, max(2, budget // 2)), budget=budget).optimize(problem)
            spent += int(res.evaluations)
            new = self._candidates(np.asarray(res.theta)[None, :], [f"{c.source} + refine({budget})"], target, mask)[0]
            out.append(new if new.r_surrogate > c.r_surrogate else c)
        out.sort(key=lambda c: -c.r_surrogate)
        return out, spent

    def evaluate(self, parameters: Any = None, target: Any = None, partial: bool = False, label: str = "given",
                 theta: Any = None) -> InversionResult:
        """An :class:`InversionResult` for given parameters (a ``{name: value}`` mapping or a physical
        vector; or normalised ``theta``) against a target, e.g. to validate known parameters."""
        if target is None or (parameters is None) == (theta is None):
            raise InvphysError("evaluate() needs a target and either parameters or theta")
        t = self.targets(target, partial)
        space = self.bundle.space
        if theta is not None:
            theta = space.check_unit(np.asarray(theta, dtype=np.float64).reshape(1, -1))
        else:
            phys = space.from_mapping(parameters) if isinstance(parameters, Mapping) else space.check(parameters)
            theta = space.normalize(phys).reshape(1, -1)
        cands = self._candidates(theta, [label], t.values[0], t.mask[0])
        return InversionResult(label=t.labels[0], method=label, target=t.values[0], mask=t.mask[0], candidates=cands,
                               parameter_names=self.parameter_names,
                               parameter_units=tuple(p.unit for p in space.parameters),
                               feature_names=self.feature_names, feature_units=self.bundle.feature_units,
                               warnings=self._warnings(t.values[0], t.mask[0]),
                               bundle_id=str(self.bundle.manifest.get("bundle_id", "")))

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

    def _simulation(self, overrides: Mapping[str, Any] | None, batch_size: int) -> tuple[Any, Any, Any]:
        """(simulator, extractor, simulator validator) for re-running candidates."""
        if batch_size < 1:
            raise InvphysError(f"batch_size must be >= 1, got {batch_size}")
        sim = self.simulator(overrides)
        ext = self.extractor(sim)
        return sim, ext, self.bundle.registry.create("validator", {"type": "simulator", "batch_size": batch_size})

    def validate(self, results: InversionResult | Sequence[InversionResult], overrides: Mapping[str, Any] | None = None,
                 batch_size: int = 16, on_run: Callable[[int], None] | None = None
                 ) -> InversionResult | list[InversionResult]:
        """Re-run every candidate through the simulator: fills ``actual``, ``r_actual`` and ``gap``.

        ``overrides`` change the recorded simulator config (e.g. ``{"arch": "cpu"}``); ``on_run(i)`` is
        called as each run finishes. Returns ``results`` (updated in place).
        """
        single = isinstance(results, InversionResult)
        items: list[InversionResult] = [results] if isinstance(results, InversionResult) else list(results)
        self._simulate([(r, c) for r in items for c in r.candidates], *self._simulation(overrides, batch_size),
                       on_run=on_run)
        return items[0] if single else items

    def _simulate(self, cands: list[tuple[InversionResult, Candidate]], sim: Any, ext: Any, validator: Any,
                  on_run: Callable[[int], None] | None = None) -> None:
        """Simulate candidates (with their results): fills ``actual``, ``r_actual``, ``gap``, ``failure``."""
        if not cands:
            return
        theta = np.array([c.theta for _, c in cands])
        if hasattr(validator, "simulate_features"):
            sim_out = validator.simulate_features(theta, sim, ext, on_run=on_run)
            actual, failures = sim_out.features, sim_out.failures
        else:
            recs = validator.validate(theta, np.array([np.where(r.mask, r.target, 0.0) for r, _ in cands]),
                                      np.array([c.predicted for _, c in cands]), sim, ext, self.bundle.scales)
            actual = np.array([np.full(len(self.feature_names), np.nan) if x.actual is None else x.actual for x in recs])
            failures = [x.failure for x in recs]
        for j, (r, c) in enumerate(cands):
            c.failure = failures[j]
            if failures[j] is None:
                c.actual = np.asarray(actual[j], dtype=np.float64)
                c.r_actual = float(masked_recovery(c.actual, r.target, self.bundle.scales, r.mask, self.bundle.kappa))
            else:
                c.actual, c.r_actual = None, float("nan")
            c.gap = c.r_surrogate - c.r_actual

    # -- simulator-in-the-loop polish -------------------------------------------------------------------
    def polish(self, results: InversionResult | Sequence[InversionResult], budget: int = 24, popsize: int = 8,
               sigma0: float = POLISH_SIGMA0, below: float = 1.0, overrides: Mapping[str, Any] | None = None,
               batch_size: int = 16, log: str | Path | None = None, seed: int = 0,
               on_batch: Callable[[int, bool], None] | None = None, confirm: int = 0,
               confirm_candidates: int = 4) -> InversionResult | list[InversionResult]:
        """Ask/tell CMA-ES on the real simulator from each result's best simulated candidate.

        Candidates not validated yet are validated first. A result whose best R_actual is below
        ``below`` gets ``budget`` new simulator runs (``popsize`` points per generation, step ``sigma0``
        in [0, 1]^d; every generation of all results is simulated as one batch, in chunks of
        ``batch_size``). A better simulated point becomes a new first candidate (source
        ``"<start> + polish"``); otherwise the start moves first: the answer is never worse. Partial
        targets are scored over their given features, as :meth:`validate` scores them. ``log``: an
        ``.npz`` file of every simulated batch, so that a stopped polish resumes (a re-run replays the
        logged batches; a larger ``budget`` replays the smaller one's). ``on_batch(runs, replayed)``
        follows each batch. Fills ``result.polish``; returns ``results`` (updated in place).

        ``confirm`` K > 0: afterwards, every result's best ``confirm_candidates`` simulated points (its
        polish's answer and the next best points its polish simulated; a result that was not polished:
        its answer alone) are simulated K more times, all in one batch through the same log, and the
        candidate with the best mean R over those K runs becomes the first candidate, with that mean as
        its ``r_actual`` (its ``actual`` stays the features of the run that found it; other candidates
        keep their single-run R). ``result.polish["confirm"]`` records ``r_selected`` (best of N),
        ``r_confirmed``, every run's R and whether the answer changed
        (:func:`~invphys.plugins.evaluators.polish.confirm`). Cost: K x candidates runs per result.
        """
        from invphys.plugins.evaluators.polish import BatchLog, Polished, polish
        from invphys.plugins.evaluators.polish import confirm as confirm_answers
        from invphys.plugins.evaluators.simulator_loop import SimulatorEvaluator

        check_polish(budget, popsize, sigma0, below, confirm, confirm_candidates)
        single = isinstance(results, InversionResult)
        items: list[InversionResult] = [results] if isinstance(results, InversionResult) else list(results)
        if log is not None and Path(log).is_dir():
            raise InvphysError(f"polish log {log} is a directory; name a file (e.g. polish.npz)")
        sim, ext, validator = self._simulation(overrides, batch_size)
        self._simulate([(r, c) for r in items for c in r.candidates if c.r_actual is None and c.failure is None],
                       sim, ext, validator)
        starts = [max(r.candidates, key=lambda c: -np.inf if c.r_actual is None or not np.isfinite(c.r_actual)
                      else c.r_actual) for r in items]
        m = len(self.feature_names)
        targets = np.array([np.where(r.mask, r.target, np.nan) for r in items], dtype=np.float64)
        theta = np.array([c.theta for c in starts], dtype=np.float64)
        r0 = np.array([np.nan if c.r_actual is None else c.r_actual for c in starts], dtype=np.float64)
        feats = np.array([np.full(m, np.nan) if c.actual is None else c.actual for c in starts], dtype=np.float64)
        chosen = ~(r0 >= below)  # NaN (the start failed) is polished too
        settings = {"budget": budget, "popsize": popsize, "sigma0": sigma0, "below": below, "seed": seed}
        key = self._polish_key(targets, theta, chosen, settings, overrides)  # not confirm: a log without it replays
        if confirm:
            settings.update(confirm=confirm, confirm_candidates=confirm_candidates)
        batches = BatchLog(None if log is None else Path(log), key, SimulatorEvaluator.from_validator(validator, sim, ext),
                           log=_polish_note, chunk=batch_size, on_batch=on_batch)
        t0 = time.perf_counter()
        if budget > 0 and chosen.any():
            pol = polish(targets, theta, r0, feats, self.bundle.scales, batches, budget, popsize, sigma0, below,
                         seed=seed, score=self._masked_score)
        else:
            pol = Polished(theta, r0, feats, np.zeros(len(items), np.int64), chosen & (budget > 0), 0.0, 0, 0, "")
        polished_theta = pol.theta.copy()
        if confirm:
            pol = confirm_answers(pol, targets, self.bundle.scales, batches, confirm, confirm_candidates,
                                  score=self._masked_score).apply(pol)
        new_theta, new_r, new_feats, runs, seconds, device = (pol.theta, pol.r_actual, pol.features, pol.runs,
                                                              pol.seconds, pol.device)
        total = int(runs.sum())
        call = {"targets": len(items), "polished": int(chosen.sum()) if budget > 0 else 0, "runs": total,
                "replayed_runs": batches.replayed_runs, "simulator_s": seconds, "device": device,
                "wall_time_s": time.perf_counter() - t0, "log": None if log is None else str(log)}
        for i, (r, start) in enumerate(zip(items, starts, strict=True)):
            if confirm:  # the answer is a confirmed candidate: the start, or a point the polish simulated
                moved = bool((pol.confirmed is not None and pol.confirmed.pick[i] >= 0) or (chosen[i] and budget > 0))
                improved = bool(moved and not np.array_equal(new_theta[i], start.theta))
            else:
                moved = bool(chosen[i] and budget > 0)
                improved = bool(chosen[i] and np.isfinite(new_r[i]) and not new_r[i] <= r0[i])
            if improved:
                cand = self._candidates(new_theta[i][None, :], [f"{start.source} + polish"], r.target, r.mask)[0]
                cand.actual, cand.r_actual = new_feats[i].copy(), float(new_r[i])
                cand.gap = cand.r_surrogate - cand.r_actual
                r.candidates.insert(0, cand)
            elif moved:
                r.candidates.insert(0, r.candidates.pop(next(j for j, c in enumerate(r.candidates) if c is start)))
                if confirm:
                    start.r_actual = float(new_r[i])
                    start.gap = start.r_surrogate - start.r_actual
            r.polish = {"polished": bool(chosen[i] and budget > 0), "improved": improved, "start_source": start.source,
                        "start_r_actual": float(r0[i]), "r_actual": float(new_r[i]), "runs": int(runs[i]),
                        "simulator_s": float(runs[i] / max(total, 1) * seconds), "device": device,
                        "settings": dict(settings), "call": call}
            if pol.confirmed is not None:
                r.polish["confirm"] = {**pol.confirmed.record(i),
                                       "selected_theta": [float(v) for v in polished_theta[i]]}
        return items[0] if single else items

    def _masked_score(self, y: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """R over each row's given features (a missing feature is NaN in ``targets``), as in :meth:`validate`."""
        given = np.isfinite(targets)
        return masked_recovery(y, np.where(given, targets, 0.0), self.bundle.scales, given, self.bundle.kappa)

    def _polish_key(self, targets: np.ndarray, theta: np.ndarray, chosen: np.ndarray, settings: dict[str, Any],
                    overrides: Mapping[str, Any] | None) -> str:
        """What a polish log was made for: bundle, simulator config, targets, starts and settings (not the
        budget: a larger budget replays the smaller one's batches)."""
        import hashlib
        import json

        head = {"bundle": self.bundle.manifest.get("bundle_id", ""), "files": self.bundle.manifest.get("files", {}),
                "simulator": self.bundle.manifest["simulator"].get("config", {}), "overrides": dict(overrides or {}),
                "settings": {k: v for k, v in settings.items() if k != "budget"}, "polished": chosen.tolist()}
        h = hashlib.sha256(json.dumps(head, sort_keys=True, default=str).encode())
        h.update(np.ascontiguousarray(targets, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(theta, dtype=np.float64).tobytes())
        return h.hexdigest()[:24]


def check_polish(budget: int, popsize: int, sigma0: float, below: float, confirm: int = 0,
                 confirm_candidates: int = 4) -> None:
    """Raise :class:`InvphysError` for polish settings that cannot run."""
    if not isinstance(confirm, (int, np.integer)) or isinstance(confirm, bool) or confirm < 0:
        raise InvphysError(f"polish confirm must be a whole number >= 0 of re-runs per candidate, got {confirm!r}")
    if (not isinstance(confirm_candidates, (int, np.integer)) or isinstance(confirm_candidates, bool)
            or confirm_candidates < 1):
        raise InvphysError(f"polish confirm_candidates must be a whole number >= 1, got {confirm_candidates!r}")
    if not isinstance(budget, (int, np.integer)) or isinstance(budget, bool) or budget < 0:
        raise InvphysError(f"polish budget must be a whole number >= 0 of simulator runs per target, got {budget!r}")
    if not isinstance(popsize, (int, np.integer)) or isinstance(popsize, bool) or popsize < 2:
        raise InvphysError(f"polish popsize must be a whole number >= 2, got {popsize!r}")
    if not (isinstance(sigma0, (int, float, np.floating)) and np.isfinite(sigma0) and sigma0 > 0):
        raise InvphysError(f"polish sigma0 must be > 0 (a step in the normalised [0, 1] parameter cube), got {sigma0!r}")
    if not (isinstance(below, (int, float, np.floating)) and 0 < below <= 1):
        raise InvphysError(f"polish below must be in (0, 1] (polish targets whose R_actual is below it), got {below!r}")


def _polish_note(message: str) -> None:
    """The polish log's messages: each batch at debug level, anything unexpected at info."""
    quiet = message.startswith("polish batch") and "other points" not in message
    (_LOG.debug if quiet else _LOG.info)(message)
