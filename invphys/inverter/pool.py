"""The candidate pool: posterior draws, the nearest training rows and local moves, scored by the ensemble.

For one target the pool holds

* the first ``draws`` truncated posterior draws of the bundle's NPE (the same draws, from the same
  per-target stream, as the posterior method's own answer and intervals), and ``draws`` more from each
  posterior method named in ``extra`` (an NPE ensemble: each member's draws from its own per-target
  stream; the intervals are then the mixture's);
* the ``neighbours`` training rows nearest the target by the recovery metric (features divided by the
  scales s_k, over the given features): where the posterior is poor (the box's faces and corners) a
  row that was really simulated near the target is often the better start;
* ``moves`` local moves: Gaussian steps of ``step`` (normalised units) around the ``starts`` best
  candidates so far, from a random stream of the target's own (:func:`~invphys.inverter.seeds.target_rng`).

Every candidate is scored ``R_surr - lam x normalised ensemble std`` (the std on the scales s_k, as
:func:`~invphys.evaluators.uncertainty.normalised_std`): the penalty keeps the answer away from
where the surrogate's members disagree, i.e. where its R is least trustworthy. With ``exact`` the
stored rows are scored by their REAL features instead (the R they really reach, no penalty: they were
simulated), and every surrogate-scored candidate loses ``margin`` more (the surrogate's optimism where
it selects), so a stored row wins where the surrogate only promises to beat it; with ``anchor`` a move
from a stored row is predicted as ``f(theta') + y_j - f(theta_j)`` (the row's residual carried over, so
the prediction starts from the row's real features). ``rows="all"`` also
offers the bundle's held-out rows as stored candidates (never for scoring those rows themselves).
The answer is the best scored candidate. Nothing depends on other targets or their order.

A stored row in the answer (any setting) reports its real features and their R against the target
(:attr:`~invphys.inverter.result.Candidate.known`, ``r_known``) next to the surrogate's R: what the
simulator gave at those parameters, up to its re-run noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError
from invphys.core.masked_recovery import masked_recovery
from invphys.core.nearest import nearest_first
from invphys.inverter.answers import Known, Pool, PosteriorAnswers
from invphys.inverter.seeds import target_rng, target_seed

#: the label ``invphys invert --method`` knows the pool by (any bundle holding a posterior method)
POOL_METHOD = "pool"
#: the stored rows a pool may offer: the bundle's training rows, or with its held-out rows too
STORED_ROWS = ("train", "all")


@dataclass(frozen=True)
class PoolSettings:
    """How a pool is built and scored. Defaults: the best of the variants measured on the fresh
    user-like sets on the CPU (docs/inverting.md); validation on the simulator decides what is claimed."""

    draws: int = 64
    neighbours: int = 16
    moves: int = 32
    starts: int = 4
    step: float = 0.03
    lam: float = 0.5
    #: other posterior methods of the bundle whose draws join the pool (an ensemble of NPEs)
    extra: tuple[str, ...] = ()
    #: score the stored rows by their real features (exact R, no penalty) instead of by the surrogate
    exact: bool = False
    #: with ``exact``: subtracted from every surrogate score (its expected optimism over the real R)
    margin: float = 0.0
    #: the stored rows: ``train`` (the bundle's training rows) or ``all`` (and its held-out rows)
    rows: str = "train"
    #: with ``exact``: a move from a stored row is predicted with that row's residual added
    anchor: bool = False

    def checked(self) -> PoolSettings:
        """``self``, or :class:`InvphysError` naming the first setting out of range."""
        for name, low in (("draws", 1), ("neighbours", 0), ("moves", 0), ("starts", 1)):
            v = getattr(self, name)
            if not is_count(v, low):
                raise InvphysError(f"pool {name} must be a whole number >= {low}, got {v!r}")
        for name, ok, rule in (("step", lambda x: 0 < x <= 0.5, "in (0, 0.5]"), ("lam", lambda x: x >= 0, ">= 0")):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not ok(float(v)):
                raise InvphysError(f"pool {name} must be a number {rule}, got {v!r}")
        for name in ("exact", "anchor"):
            v = getattr(self, name)
            if v not in (True, False, 0, 1) or isinstance(v, float):
                raise InvphysError(f"pool {name} must be true or false, got {v!r}")
        if self.anchor and not self.exact:
            raise InvphysError("pool anchor applies only with exact (stored rows scored by their real features)")
        m = self.margin
        if isinstance(m, bool) or not isinstance(m, (int, float, np.number)) or not 0 <= float(m) < 1:
            raise InvphysError(f"pool margin must be a number in [0, 1), got {m!r}")
        if float(m) and not self.exact:
            raise InvphysError("pool margin applies only with exact (stored rows scored by their real features)")
        if self.rows not in STORED_ROWS:
            raise InvphysError(f"pool rows must be one of {', '.join(STORED_ROWS)}, got {self.rows!r}")
        extra = (self.extra,) if isinstance(self.extra, str) else self.extra
        if not isinstance(extra, (list, tuple)) or not all(isinstance(e, str) and e for e in extra):
            raise InvphysError(f"pool extra must be a list of method labels, got {self.extra!r}")
        return replace(self, extra=tuple(extra), exact=bool(self.exact), margin=float(m), anchor=bool(self.anchor))

    def with_(self, **kw: Any) -> PoolSettings:
        return replace(self, **kw).checked()


def nearest_rows(z_train: np.ndarray, values: np.ndarray, mask: np.ndarray, scales: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` training rows nearest the target (scaled features, given ones only), nearest
    first, ties by row index; ``z_train`` (N, M): the training features divided by the scales."""
    if k <= 0 or not len(z_train):
        return np.zeros(0, dtype=np.int64)
    zt = np.where(mask, values, 0.0) / np.maximum(scales, 1e-12)
    diff = z_train - zt[None, :]
    if not mask.all():  # a complete target keeps them all (no second N x M temporary: the same d2, faster)
        diff = np.where(mask[None, :], diff, 0.0)
    d2 = np.einsum("ij,ij->i", diff, diff)
    return nearest_first(np.where(np.isfinite(d2), d2, np.inf), k).astype(np.int64)


class PoolAnswers(PosteriorAnswers):
    """The candidate pool over the posterior method ``posterior_label`` (module docstring)."""

    def __init__(self, inv: Any, label: str, entry: dict[str, Any], plugin: Any, posterior_label: str,
                 settings: PoolSettings) -> None:
        super().__init__(inv, label, entry, plugin)
        self.posterior_label, self.settings = posterior_label, settings.checked()
        self.answer_draws = self.settings.draws
        self.members = [self._member(m) for m in self.settings.extra]
        splits = ("train", "test") if self.settings.rows == "all" else ("train",)
        try:
            parts = [self.bundle.data(split) for split in splits]
        except InvphysError as e:
            raise InvphysError(f"method {self.label!r}: pool rows {self.settings.rows!r}: {e}") from None
        theta, y = (np.concatenate([p[i] for p in parts]) for i in (0, 1))
        ok = np.all(np.isfinite(y), axis=1)
        self.train_theta = np.asarray(theta[ok], dtype=np.float64)
        self.train_y = np.asarray(y[ok], dtype=np.float64)
        self.z_train = self.train_y / np.maximum(self.bundle.scales, 1e-12)

    def _member(self, label: str) -> Any:
        """The plugin of the extra posterior method ``label`` (an NPE of the same bundle)."""
        from invphys.inverter.draws import has_posterior

        entry = self.bundle.methods.get(label)
        plugin = None if entry is None or entry.get("type") == POOL_METHOD else self.inv._plugin(label, entry)[0]
        if plugin is None or not has_posterior(plugin):
            raise InvphysError(f"method {self.label!r}: extra posterior {label!r} is not a posterior method "
                               f"of the bundle ({', '.join(self.bundle.methods)})")
        return plugin

    def draw(self, values: np.ndarray, masks: np.ndarray, seed: int, n: int) -> tuple[list[np.ndarray], Any]:
        """The posterior's draws, with ``draws`` from each extra posterior (its own per-target stream)
        placed after the first ``draws``: the pool's candidates (and the intervals) use them all."""
        from invphys.inverter.draws import sample_posterior

        conds, d = super().draw(values, masks, seed, n)
        if not self.members:
            return conds, d
        k = self.settings.draws
        blocks = [d.samples[:, :k]]
        for label, plugin in zip(self.settings.extra, self.members, strict=True):
            seeds = [target_seed(seed, label, v, m, "posterior") for v, m in zip(values, masks, strict=True)]
            blocks.append(sample_posterior(plugin, conds, seeds, k, whole_rounds=False).samples)  # no fraction read
        d.samples = np.concatenate([*blocks, d.samples[:, k:]], axis=1)
        return conds, d

    @property
    def lam(self) -> float:
        return float(self.settings.lam)

    def max_top_k(self) -> int:
        s = self.settings
        return s.draws * (1 + len(s.extra)) + s.neighbours + s.moves

    def score(self, thetas: np.ndarray, values: np.ndarray, mask: np.ndarray, offset: np.ndarray | None = None
              ) -> np.ndarray:
        """(P,) R_surr over the given features minus lam x the normalised ensemble std (and, with
        ``exact``, minus the margin); ``offset`` (P, M): added to the prediction (an anchored move)."""
        from invphys.evaluators.uncertainty import normalised_std

        mean, std = self.bundle.surrogate.predict_with_uncertainty(np.clip(thetas, 0.0, 1.0))
        if offset is not None:
            mean = mean + offset
        r = masked_recovery(mean, values, self.bundle.scales, mask, self.bundle.kappa)
        if self.settings.exact and self.settings.margin:
            r = r - self.settings.margin
        return r - self.lam * normalised_std(std, self.bundle.scales) if self.lam else r

    def stored_score(self, rows: np.ndarray, values: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(k,) the exact R of stored rows (their real features; no penalty): what their answer reaches."""
        return masked_recovery(self.train_y[rows], values, self.bundle.scales, mask, self.bundle.kappa)

    def from_draws(self, values: np.ndarray, mask: np.ndarray, top_k: int, seed: int, samples: np.ndarray,
                   cond: np.ndarray) -> Pool:
        s = self.settings
        rows = nearest_rows(self.z_train, values, mask, self.bundle.scales, s.neighbours)
        near = self.train_theta[rows]
        n_post = s.draws * (1 + len(s.extra))
        thetas = np.concatenate([samples[:n_post], near])
        exact = self.stored_score(rows, values, mask)
        sources = [f"{self.label} (posterior)"] * n_post + [f"{self.label} (neighbour)"] * len(rows)
        known: list[Known | None] = [None] * n_post
        known += [Known(self.train_y[j], float(r)) for j, r in zip(rows, exact, strict=True)]
        if s.exact:
            scores = np.concatenate([self.score(thetas[:n_post], values, mask), exact])
        else:
            scores = self.score(thetas, values, mask)
        if s.moves:
            moved, start = self._moves(thetas, scores, values, mask, seed)
            offset = None
            if s.anchor:  # the residual of a stored start (its real features less the surrogate's), else 0
                resid = np.zeros((len(thetas), len(values)))
                resid[n_post:] = self.train_y[rows] - self.bundle.surrogate.predict(near)
                offset = resid[start]
            scores = np.concatenate([scores, self.score(moved, values, mask, offset)])
            thetas = np.concatenate([thetas, moved])
            sources += [f"{self.label} (move)"] * len(moved)
            known += [None] * len(moved)
        order = np.lexsort((np.arange(len(scores)), -scores))  # best first, ties by position (deterministic)
        keep = order[:1] if top_k == 1 else order
        return Pool(thetas[keep], [sources[i] for i in keep], len(thetas), [known[i] for i in keep])

    def _moves(self, thetas: np.ndarray, scores: np.ndarray, values: np.ndarray, mask: np.ndarray, seed: int
               ) -> tuple[np.ndarray, np.ndarray]:
        """(moves, the index into ``thetas`` of each move's start)."""
        s = self.settings
        starts = np.lexsort((np.arange(len(scores)), -scores))[:s.starts]
        rng = target_rng(seed, self.label, values, mask, "moves")
        steps = rng.normal(0.0, s.step, size=(s.moves, thetas.shape[1]))
        start = starts[np.arange(s.moves) % len(starts)]
        return np.clip(thetas[start] + steps, 0.0, 1.0), start
