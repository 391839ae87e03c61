"""One answering object per kind of method, the way sbi separates posteriors from their trainers.

* :class:`PosteriorAnswers`: a trained posterior (sbi's NPE): truncated draws, the method's answer among them;
* :class:`LookupAnswers`: a dataset baseline without a posterior (nearest rows, local fits);
* :class:`PolicyAnswers`: a bundle's goal-conditioned policy, rolled out;
* :class:`SearchAnswers`: an optimiser searching the surrogate (CMA-ES, warm start, nevergrad, ...).

Each answers ONE target at a time from random streams of its own
(:func:`~invphys.inverter.seeds.target_seed`): an answer never depends on the other targets of a batch.
``answer`` returns the candidate :class:`Pool` (thetas, sources, evaluations spent, the stored rows among
them) and the :class:`Uncertainty`.
"""

from __future__ import annotations

import contextlib
import warnings
import weakref
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.masked_recovery import MaskedRecovery, masked_recovery
from invphys.inverter.seeds import target_seed
from invphys.inverter.uncertainty import NEIGHBOUR_ROWS, Uncertainty


@dataclass(frozen=True, eq=False)  # its features are an array: no elementwise ==
class Known:
    """A candidate that is a stored row of the bundle (simulated when its data was made): the row's real
    features ``features`` (M,) and their R against the target ``r``."""

    features: np.ndarray
    r: float


class Pool(NamedTuple):
    """One target's candidates: thetas (P, d), their sources, the evaluations spent and, row for row, the
    stored rows among them (:class:`Known`; None: not a stored row; ``known`` None: none is)."""

    thetas: np.ndarray
    sources: list[str]
    spent: int
    known: list[Known | None] | None = None


#: most candidates a policy or a search gives per target (each a rollout set or a whole search)
MAX_TOP_K = 64
#: targets whose posterior draws are made together (bounds the memory of one batch)
DRAW_BATCH = 64
#: most draws (targets x draws per target) held at once
DRAW_ROWS = 2**18
#: a posterior answer chooses among the first draws of a run of (at least) this many, whatever the intervals'
#: draws: a run's rejection cap grows with its length, so where most of a target's posterior lies outside the
#: box the first draws of a shorter run hold more clipped ones (the default intervals' 256: one run)
ANSWER_RUN_DRAWS = 256


@contextlib.contextmanager
def quiet_cma() -> Iterator[None]:
    """Silence cma's warning about an injected start point (a warm start injects one on purpose)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="orphanated injected solution")
        yield


class MethodAnswers:
    """Base: a bundle method (``label``, its manifest ``entry``) answering targets through ``inv``."""

    kind: ClassVar[str] = ""

    def __init__(self, inv: Any, label: str, entry: dict[str, Any]) -> None:
        self.inv, self.label, self.entry = inv, label, entry
        self.bundle = inv.bundle

    def max_top_k(self) -> int:
        return MAX_TOP_K

    def check_top_k(self, top_k: int) -> None:
        most = self.max_top_k()
        if top_k > most:
            raise InvphysError(f"top_k {top_k} is more than method {self.label!r} can give: at most {most} "
                               f"distinct candidates per target ({self.kind})")

    def penalty(self) -> float:
        """The entry's ``uncertainty_penalty`` lambda (0: none; a bundle made before it was kept: none)."""
        lam = self.entry.get("uncertainty_penalty", 0.0)
        if isinstance(lam, bool) or not isinstance(lam, (int, float)) or not 0 <= lam < float("inf"):
            raise InvphysError(f"method {self.label!r}: uncertainty_penalty must be a number >= 0, got {lam!r}")
        if lam and not hasattr(self.bundle.surrogate, "predict_with_uncertainty"):
            raise InvphysError(f"method {self.label!r}: uncertainty_penalty needs a surrogate with uncertainty "
                               f"(the ensemble)")
        return float(lam)

    def seed(self, seed: int, values: np.ndarray, mask: np.ndarray, stream: str) -> int:
        return target_seed(seed, self.label, values, mask, stream)

    def goal(self, values: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The target with missing features as the training mean (what amortised methods condition on)."""
        return np.where(mask, values, np.asarray(self.bundle.manifest["features"]["mean"], dtype=np.float64))

    def answer(self, values: np.ndarray, mask: np.ndarray, top_k: int, seed: int, draws: int
               ) -> tuple[Pool, Uncertainty]:
        raise NotImplementedError

    def answer_all(self, values: np.ndarray, masks: np.ndarray, top_k: int, seed: int, draws: int
                   ) -> Iterator[tuple[Pool, Uncertainty]]:
        """:meth:`answer` for every row of ``values`` (B, M), in order; a method may share work across
        the targets as long as no answer depends on the others."""
        for v, m in zip(values, masks, strict=True):
            yield self.answer(v, m, top_k, seed, draws)


class PosteriorAnswers(MethodAnswers):
    """A dataset baseline holding a posterior: ``draws`` truncated draws per target (at least the
    method's own ``samples``); the answer is chosen among the first ``samples`` as the method says."""

    kind = "posterior"

    def __init__(self, inv: Any, label: str, entry: dict[str, Any], plugin: Any) -> None:
        super().__init__(inv, label, entry)
        self.plugin = plugin
        self.k = self.answer_draws = int(getattr(plugin.config, "samples", 64))

    def max_top_k(self) -> int:
        return self.k

    #: the method whose per-target stream the draws come from (a pool draws the NPE's own draws)
    posterior_label: str = ""
    #: draws per target the answer itself uses (before the intervals' ``draws``)
    answer_draws: int = 1
    #: (B, M) observation noise (std; NaN: none), row for row the targets the next :meth:`answer_all`
    #: answers, or None: a target with noise is drawn from its noisy posterior (:mod:`~invphys.inverter.noise`)
    noise: np.ndarray | None = None
    _noise_rows: np.ndarray | None = None
    #: (values, mask, std) of the noisy target being answered (None: an exact one), for :meth:`_choose`
    _noisy_now: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def draw(self, values: np.ndarray, masks: np.ndarray, seed: int, n: int) -> tuple[list[np.ndarray], Any]:
        """(conditions per target, :class:`~invphys.inverter.draws.PosteriorDraws`) of every target, drawn
        together (each from its own stream: the same draws as alone)."""
        from invphys.inverter.noise import posterior_draws

        return posterior_draws(self.bundle, self.plugin, self.posterior_label or self.label, values, masks,
                               self._noise_rows, seed, n)

    def answer(self, values: np.ndarray, mask: np.ndarray, top_k: int, seed: int, draws: int
               ) -> tuple[Pool, Uncertainty]:
        return next(iter(self.answer_all(values[None, :], mask[None, :], top_k, seed, draws)))

    def answer_all(self, values: np.ndarray, masks: np.ndarray, top_k: int, seed: int, draws: int
                   ) -> Iterator[tuple[Pool, Uncertainty]]:
        """Each target's pool and uncertainty. The answer comes from a run of :data:`ANSWER_RUN_DRAWS` draws
        (or its own ``samples``, if more), so it does not depend on ``draws``; the intervals keep the first
        ``max(samples, draws)`` draws of the same run (and a pool's extra members' draws), or of their own longer
        one."""
        kept = max(self.answer_draws, draws)
        na = max(self.answer_draws, ANSWER_RUN_DRAWS)
        n = max(na, kept)
        step = max(1, min(DRAW_BATCH, DRAW_ROWS // n))
        for a in range(0, len(values), step):
            v, m = values[a:a + step], masks[a:a + step]
            self._noise_rows = None if self.noise is None else self.noise[a:a + step]
            conds, d = self.draw(v, m, seed, n)
            answer_draws = d.samples if n == na else self.draw(v, m, seed, na)[1].samples
            kept_cols = d.samples.shape[1] - (n - kept)  # a run longer than asked: its last draws are not kept
            for i in range(len(v)):
                std = None if self._noise_rows is None else self._noise_rows[i]
                noisy = std is not None and bool(np.nan_to_num(std, nan=0.0).max() > 0)
                self._noisy_now = (v[i], m[i], std) if noisy and std is not None else None
                unc = Uncertainty("posterior", d.samples[i][:kept_cols], outside_fraction=float(d.outside_fraction[i]),
                                  clipped=int(d.clipped[i]), completions=int(d.completions[i]))
                yield self.from_draws(v[i], m[i], top_k, seed, answer_draws[i], conds[i]), unc

    def from_draws(self, values: np.ndarray, mask: np.ndarray, top_k: int, seed: int, samples: np.ndarray,
                   cond: np.ndarray) -> Pool:
        """The candidate pool of one target from its draws (S, d)."""
        first = samples[:self.k]
        theta, spent = self._choose(first, cond[0], self.goal(values, mask))
        pool = theta[None, :] if top_k == 1 and mask.all() else np.concatenate([theta[None, :], first])
        return Pool(pool, [self.label] * len(pool), spent)

    def _choose(self, first: np.ndarray, cond: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, int]:
        """The method's answer among its draws (mean, best log-prob, best by the surrogate; for a noisy
        target, other than mean: the most likely under its noise) and the evaluations spent (as the
        baseline counts them: its candidates and the answer)."""
        how = getattr(self.plugin.config, "answer", "best_surrogate")
        if how == "mean":
            return first.mean(axis=0), 1
        if self._noisy_now is not None:  # the draw the noise makes likeliest (the prior is flat on the box)
            from invphys.inverter.noise import log_likelihood

            values, mask, std = self._noisy_now
            ll = log_likelihood(self.bundle.surrogate, first, values, mask, std, self.bundle.scales)
            return first[int(np.argmax(ll))], len(first) + 1
        if how == "best_log_prob":
            from invphys.inverter.draws import log_prob

            return first[int(np.argmax(log_prob(self.plugin, first, cond)))], 1
        from invphys.plugins.baselines._base import best_by_surrogate

        sur = self.bundle.surrogate
        lam = self.penalty() or float(getattr(self.plugin.config, "uncertainty_penalty", 0.0) or 0.0)
        predict, penalty = sur.predict, None
        if lam > 0:
            from invphys.evaluators.uncertainty import UncertaintyPenalty

            pen = UncertaintyPenalty(sur, self.bundle.scales, lam)
            predict, penalty = pen.predict, pen.penalty
        best, _ = best_by_surrogate(first[None], goal[None], self.bundle.scales, predict, penalty)
        return first[int(best[0])], len(first) + 1


#: :class:`StoredRows` per loaded bundle
_STORED: weakref.WeakKeyDictionary[Any, StoredRows] = weakref.WeakKeyDictionary()


class StoredRows:
    """The bundle's stored rows found by their exact parameters: a candidate that is one of them (a
    lookup's answer) carries the row's real features and their R (:class:`Known`)."""

    def __init__(self, bundle: Any) -> None:
        theta, y = bundle.data("train")
        self.bundle, self.y = bundle, np.asarray(y, dtype=np.float64)
        self._index = {np.asarray(t, dtype=np.float64).tobytes(): i for i, t in enumerate(theta)}

    @classmethod
    def of(cls, bundle: Any) -> StoredRows:
        """One per loaded bundle (its index takes a few milliseconds to build)."""
        if bundle not in _STORED:
            _STORED[bundle] = cls(bundle)
        return _STORED[bundle]

    def known(self, thetas: np.ndarray, values: np.ndarray, mask: np.ndarray) -> list[Known | None]:
        """Per theta: the stored row it is (its real features and their R), or None."""
        out: list[Known | None] = []
        for t in thetas:
            i = self._index.get(np.asarray(t, dtype=np.float64).tobytes())
            if i is None or not np.all(np.isfinite(self.y[i])):
                out.append(None)
                continue
            r = masked_recovery(self.y[i][None], values, self.bundle.scales, mask, self.bundle.kappa)[0]
            out.append(Known(self.y[i], float(r)))
        return out


class LookupAnswers(MethodAnswers):
    """A dataset baseline without a posterior, asked one target at a time; a seeded baseline gets the
    target's own seed. Its spread: the parameters of the nearest training rows (when it has them). An
    answer that is a stored training row carries its real features (:class:`StoredRows`)."""

    kind = "lookup"

    def __init__(self, inv: Any, label: str, entry: dict[str, Any], plugin: Any) -> None:
        super().__init__(inv, label, entry)
        self.plugin = plugin
        self._stored: StoredRows | None = None

    def max_top_k(self) -> int:
        return max(1, int(self.plugin.evaluation_budget))

    def answer(self, values: np.ndarray, mask: np.ndarray, top_k: int, seed: int, draws: int
               ) -> tuple[Pool, Uncertainty]:
        from invphys.plugins.baselines import answer_with_penalty

        goal = self.goal(values, mask)[None, :]
        cfg = self.plugin.config
        if "seed" in type(cfg).model_fields:
            self.plugin.config = cfg.model_copy(update={"seed": self.seed(seed, values, mask, "lookup")})
        try:
            sur, lam = self.bundle.surrogate, self.penalty()
            if lam:  # the entry's penalty (an optimiser entry's uncertainty_penalty, as the invert stage applied it)
                from invphys.evaluators.uncertainty import UncertaintyPenalty

                pen = UncertaintyPenalty(sur, self.bundle.scales, lam)
                ans = self.plugin.answer(goal, pen.predict, pen.penalty)
            else:
                ans = answer_with_penalty(self.plugin, goal, sur.predict, sur, self.bundle.scales,
                                          f"method {self.label!r}")
        finally:
            self.plugin.config = cfg
        spent = int(ans.evaluations[0]) + 1
        if top_k == 1 and mask.all():
            pool = ans.theta[:1]
        else:
            pool = np.concatenate([ans.theta[:1], ans.candidates[0]])
        return Pool(pool, [self.label] * len(pool), spent, self._known(pool, values, mask)), self._spread(goal)

    def _known(self, pool: np.ndarray, values: np.ndarray, mask: np.ndarray) -> list[Known | None] | None:
        if self._stored is None:
            try:
                self._stored = StoredRows.of(self.bundle)
            except InvphysError:  # a bundle without its training rows: nothing known
                return None
        return self._stored.known(pool, values, mask)

    def _spread(self, goal: np.ndarray) -> Uncertainty:
        if not hasattr(self.plugin, "neighbours") or getattr(self.plugin, "_theta", None) is None:
            return Uncertainty("none", note=f"{self.label} answers with a point")
        cfg = self.plugin.config
        self.plugin.config = cfg.model_copy(update={"k": NEIGHBOUR_ROWS})
        try:
            idx, _ = self.plugin.neighbours(goal)
        finally:
            self.plugin.config = cfg
        return Uncertainty("neighbours", np.asarray(self.plugin._theta[idx[0]], dtype=np.float64),
                           note=f"the parameters of the {idx.shape[1]} training rows nearest the target")


class PolicyAnswers(MethodAnswers):
    """A bundle policy: its deterministic rollout (top_k 1), or with stochastic rollouts and the bundle's
    other policies the visited states as candidates; every rollout of one target alone."""

    kind = "policy"

    def answer(self, values: np.ndarray, mask: np.ndarray, top_k: int, seed: int, draws: int
               ) -> tuple[Pool, Uncertainty]:
        runner = self.inv._runner(self.label)
        none = Uncertainty("none", note=f"{self.label} is a policy: it answers with a point")
        goal = np.where(mask, values, runner.mean)[None, :]
        if top_k == 1:
            points, _, _ = runner.rollout(goal, mask[None, :]).best()
            return Pool(runner.space.to_theta(points), [self.label], runner.horizon), none
        rollouts = max(8, 4 * top_k)
        ro = runner.rollout(goal, mask[None, :], rollouts=rollouts, seed=self.seed(seed, values, mask, "rollout"))
        theta = runner.space.to_theta(ro.points.reshape(-1, runner.dim))
        srcs = [f"{self.label} (rollout {r + 1})" for r in range(rollouts) for _ in range(runner.horizon)]
        thetas, spent = [theta], rollouts * runner.horizon
        for other in self.inv._policy_labels():
            if other == self.label:
                continue
            r2 = self.inv._runner(other)
            pts = r2.rollout(np.where(mask, values, r2.mean)[None, :], mask[None, :],
                             seed=target_seed(seed, other, values, mask, "rollout")).points
            thetas.append(r2.space.to_theta(pts.reshape(-1, r2.dim)))
            srcs += [other] * len(thetas[-1])
            spent += r2.horizon
        return Pool(np.concatenate(thetas), srcs, spent), none


class SearchAnswers(MethodAnswers):
    """An optimiser on the surrogate: ``top_k`` searches per target, each from its own seed, scored with
    R - lambda x the ensemble's normalised std where the entry has an ``uncertainty_penalty`` (as the
    invert stage scores it). An entry with a ``start`` (a spec's ``evaluation.methods`` refinement) is one
    ask/tell CMA-ES from that method's answer, as the validate stage refines."""

    kind = "search"

    def __init__(self, inv: Any, label: str, entry: dict[str, Any], plugin: Any) -> None:
        super().__init__(inv, label, entry)
        self.plugin = plugin

    def max_top_k(self) -> int:
        return 1 if self.entry.get("start") else MAX_TOP_K

    def answer(self, values: np.ndarray, mask: np.ndarray, top_k: int, seed: int, draws: int
               ) -> tuple[Pool, Uncertainty]:
        from invphys.core.spaces import build_problem

        note = Uncertainty("none", note=f"{self.label} is a search: it answers with a point")
        if self.entry.get("start"):
            return self._refine(values, mask, seed), note
        entry, lam = self.entry, self.penalty()
        space = self.bundle.search_space(entry["space"])
        predict = self.bundle.predictor(entry["space"], entry.get("evaluator", "shared"))
        latent = None if entry["space"] == "raw" else self.bundle.latent(entry["space"])
        budget = int(getattr(self.plugin, "evaluation_budget", 0) or getattr(self.plugin.config, "budget", 0) or 5000)
        m = self.bundle.manifest["features"]
        mean, std = np.asarray(m["mean"]), np.asarray(m["std"])
        goal = np.where(mask, values, mean)
        objective = MaskedRecovery(goal, self.bundle.scales, mask, self.bundle.kappa)
        thetas, srcs, spent = [], [], 0
        for r in range(top_k):
            s = self.seed(seed, values, mask, f"search:{r}")
            problem = build_problem(space, objective, budget, surrogate=self.bundle.surrogate, latent=latent,
                                    predict=predict, target=goal, seed=s, feature_mean=mean, feature_std=std)
            if lam:
                from invphys.evaluators.uncertainty import penalised_problem

                problem = penalised_problem(problem, self.bundle.surrogate, self.bundle.scales, lam)
            with quiet_cma():
                res = self.plugin.optimize(problem)
            thetas.append(np.clip(np.asarray(res.theta, dtype=np.float64), 0.0, 1.0))
            srcs.append(self.label if top_k == 1 else f"{self.label} (search {r + 1})")
            spent += int(res.evaluations)
        return Pool(np.array(thetas), srcs, spent), note

    def _refine(self, values: np.ndarray, mask: np.ndarray, seed: int) -> Pool:
        """CMA-ES (ask/tell, the entry's budget, popsize and sigma0) on the surrogate from the start method's
        answer, seeded from (seed, the target) like the validate stage's refinement of that target."""
        from invphys.evaluators.simulator_loop import refine_targets
        from invphys.evaluators.uncertainty import UncertaintyPenalty

        start = self.entry["start"]
        methods = self.bundle.methods
        if start not in methods or start == self.label or methods[start].get("start"):
            raise InvphysError(f"method {self.label!r}: its start {start!r} is not a method of this bundle that "
                               f"answers by itself (methods: {', '.join(methods)})")
        first, _ = self.inv._answers(start, methods[start]).answer(values, mask, 1, seed, 0)
        cfg = self.entry.get("config") or {}
        b = self.bundle
        pen = UncertaintyPenalty(b.surrogate, b.scales, self.penalty())
        goal = self.goal(values, mask)

        def score(y: np.ndarray, t: np.ndarray) -> np.ndarray:
            return masked_recovery(y, t, b.scales, mask, b.kappa) - pen.penalty(y)

        with quiet_cma():
            got = refine_targets(goal[None, :], first.thetas[:1], b.scales, pen.predict, int(cfg.get("budget", 64)),
                                 int(cfg.get("popsize", 8)), float(cfg.get("sigma0", 0.1)), seed=seed, kappa=b.kappa,
                                 score=score)[0]
        return Pool(np.clip(got.theta, 0.0, 1.0)[None, :], [self.label], int(first.spent) + got.evaluated)
