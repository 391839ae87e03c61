"""The ``corrected`` refine strategy: a surrogate corrected by the target's own runs, searched in a trust region.

After every batch, the bundle's surrogate ``f`` is corrected by the real residuals ``r_j = y_j - f(theta_j)``
of the points whose features are known for this target (its simulated runs, its known starts and the
stored training rows nearest the search centre ``c``), kernel-weighted in parameter space (output space
mapping): by default a weighted ridge fit of a local linear model around the centre::

    f_c(theta) = f(theta) + a + B (theta - c) / h,   weights w_j = exp(-|theta_j - c|^2 / (2 h^2))

(``prior``: the weight of a zero offset, ``ridge``: of zero slopes: with few points near the centre the
correction shrinks to nothing), or (``linear=False``) the local constant ``f(theta) + sum_j w_j(theta) r_j /
(prior + sum_j w_j(theta))``. The bandwidth ``h`` adapts to the spread of the points near the centre (never
below the trust radius). The next batch minimises ``f_c``'s misfit to the target (the recovery score)
around the best simulated point, at several trust radii (uniform draws in each box, then draws around the
best of them: thousands of batched surrogate evaluations on the CPU), picked greedily best-first with a
minimum spacing, a point around the best known point in another basin (``second``), and a few Gaussian
(CMA-ES-like) perturbations for diversity. The trust radius grows after a batch that improved the best
simulated score and shrinks after one that did not (and restarts at its first value when it falls below
its floor). The answer stays the best SIMULATED point (:func:`~invphys.evaluators.stream_refine.stream_refine`
keeps it), so it is never worse than the best start.

Everything a search draws comes from its own generator seeded by the target, and it only sees its own
points in ask order: the same target gets the same runs whatever the order, batch size or other targets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class CorrectedSettings:
    """The ``corrected`` strategy's knobs (unit-cube lengths; ``evals``: surrogate evaluations per batch)."""

    popsize: int = 8
    radius0: float = 0.04
    radius_min: float = 0.004
    radius_max: float = 0.3
    scales: tuple[float, ...] = (0.25, 1.0, 2.0)
    evals: int = 1536
    perturb: int = 2
    neighbours: int = 16
    prior: float = 0.05
    grow: float = 1.5
    shrink: float = 0.5
    linear: bool = True    # the residual as a local linear model around the centre (else a local constant)
    ridge: float = 0.2     # the linear model's ridge (pseudo-weight on slopes per bandwidth)
    second: int = 1        # points per batch around the best known point at least second_gap from the centre
    second_gap: float = 0.15
    second_evals: int = 512   # surrogate evaluations for the point in the other basin (a third of ``evals``)
    correct: bool = True   # False: the plain surrogate (for comparisons; the strategy without its point)


def corrected_settings(options: dict[str, Any]) -> CorrectedSettings:
    """:class:`CorrectedSettings` from ``options`` by name, checked (an unknown name or a bad value: one line)."""
    from dataclasses import fields

    from invphys.core.errors import InvphysError

    known = {f.name: f for f in fields(CorrectedSettings)}
    bad = sorted(set(options) - set(known))
    if bad:
        raise InvphysError(f"unknown corrected-refine option(s) {', '.join(bad)} (known: {', '.join(known)})")
    try:
        given: dict[str, Any] = {k: tuple(float(x) for x in v) if k == "scales" else v for k, v in options.items()}
        s = CorrectedSettings(**given)
        ok = (int(s.popsize) >= 1 and 0 < s.radius_min <= s.radius0 <= s.radius_max <= 1 and len(s.scales) >= 1
              and all(x > 0 for x in s.scales) and int(s.evals) >= 1 and int(s.perturb) >= 0 and int(s.second_evals) >= 1
              and int(s.neighbours) >= 0 and int(s.second) >= 0 and s.second_gap > 0 and s.prior > 0 and s.grow >= 1 and 0 < s.shrink < 1)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InvphysError(f"corrected-refine options out of range: {options} (need 0 < radius_min <= radius0 <= "
                           "radius_max <= 1, scales > 0, evals >= 1, prior > 0, grow >= 1, 0 < shrink < 1)")
    return s


class CorrectedSearch:
    """One target's search (ask/tell, as :func:`~invphys.evaluators.stream_refine.stream_refine` drives it).

    ``predict(theta (B, d)) -> (B, M)`` the surrogate; ``score(y (B, M), targets (B, M)) -> (B,)`` the
    recovery; ``rows``: (theta, residual y - f(theta)) of stored rows whose features are real (e.g. the
    bundle's training rows; :func:`row_residuals`), or None.
    """

    def __init__(self, t: Any, predict: Callable[[np.ndarray], np.ndarray],
                 score: Callable[[np.ndarray, np.ndarray], np.ndarray],
                 rows: tuple[np.ndarray, np.ndarray] | None = None,
                 settings: CorrectedSettings | None = None) -> None:
        self.t, self.predict, self.score = t, predict, score
        self.s = settings or CorrectedSettings()
        self.rows = rows
        self.rng = np.random.default_rng(int(t.seed) % (2**63))
        self.radius = self.s.radius0
        self.d = int(np.asarray(t.starts).shape[1])
        self._pred: list[np.ndarray] = []   # f(theta) of t.points[i], i < len(self._pred)

    # -- the corrected surrogate ---------------------------------------------------------------------
    def _data(self, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(theta (n, d), residual (n, M)) of the target's points with real features and the stored rows
        nearest ``centre``."""
        pts = self.t.points
        new = pts[len(self._pred):]
        if new:
            pred = np.asarray(self.predict(np.array([p[0] for p in new])), float)
            self._pred.extend(pred)
        m = len(self.t.target)
        th = np.array([p[0] for p in pts], float).reshape(-1, self.d)
        res = np.array([p[2] - f for p, f in zip(pts, self._pred, strict=True)], float).reshape(-1, m)
        ok = np.all(np.isfinite(res), axis=1)
        th, res = th[ok], res[ok]
        if self.rows is not None and self.s.neighbours > 0 and len(self.rows[0]):
            rt, rr = self.rows
            near = _nearest(rt, centre, self.s.neighbours)
            near = near[np.all(np.isfinite(rr[near]), axis=1)]
            th, res = np.vstack([th, rt[near]]), np.vstack([res, rr[near]])
        return th, res

    def _bandwidth(self, th: np.ndarray, centre: np.ndarray) -> float:
        """The median distance from ``centre`` of its 2d nearest known points, at least the trust radius."""
        if not len(th):
            return self.radius
        dist = np.sort(np.sqrt(((th - centre) ** 2).sum(1)))[:2 * self.d]
        return float(np.clip(max(np.median(dist), self.radius), 1e-3, 0.5))

    def corrected(self, x: np.ndarray, th: np.ndarray, res: np.ndarray, h: float, centre: np.ndarray,
                  beta: np.ndarray | None = None) -> np.ndarray:
        """``f_c`` at ``x`` (B, d) from known points ``th`` and their residuals ``res`` (``beta``: the local
        linear fit :func:`_local_linear` of these, when already made)."""
        f = np.asarray(self.predict(x), float)
        if not self.s.correct or not len(th):
            return f
        if self.s.linear:
            if beta is None:
                beta = _local_linear(th, res, centre, h, self.s.prior, self.s.ridge)
            return f + beta[0] + ((x - centre) / h) @ beta[1:]
        d2 = (x * x).sum(1)[:, None] + (th * th).sum(1)[None, :] - 2.0 * x @ th.T
        w = np.exp(-np.maximum(d2, 0.0) / (2.0 * h * h))
        return f + (w @ res) / (self.s.prior + w.sum(1))[:, None]

    def _fit(self, y: np.ndarray) -> np.ndarray:
        sc = np.asarray(self.score(y, np.tile(self.t.target, (len(y), 1))), float)
        return np.where(np.isfinite(sc), sc, -np.inf)

    # -- ask / tell ----------------------------------------------------------------------------------
    def ask(self, left: int) -> np.ndarray:
        """The next batch (at most ``popsize`` and ``left`` points, in [0, 1]^d)."""
        q = min(self.s.popsize, left)
        if q <= 0:
            return np.empty((0, self.d))
        centre = np.asarray(self.t.theta, float)
        th, res = self._data(centre)
        h = self._bandwidth(th, centre)
        pool, fit = self._candidates(centre, th, res, h, self.radius)
        n_pert = min(self.s.perturb, q - 1) if q > 1 else 0
        other = self._second_centre(centre)
        n_second = 0 if other is None else max(0, min(self.s.second, q - n_pert - 1))
        gap = max(1e-4, 0.1 * self.radius)
        chosen = _spread(pool, fit, q - n_pert - n_second, gap, th)
        if n_second and other is not None:   # a few points in the best other basin known
            th2, res2 = self._data(other)
            pool2, fit2 = self._candidates(other, th2, res2, self._bandwidth(th2, other), self.s.radius0,
                                           self.s.second_evals)
            chosen += _spread(pool2, fit2, n_second, gap, np.vstack([th2, *chosen]) if chosen else th2)
        while len(chosen) < q:   # CMA-ES-like perturbations of the centre (and fill-ups)
            chosen.append(np.clip(centre + 0.5 * self.radius * self.rng.standard_normal(self.d), 0.0, 1.0))
        return np.array(chosen[:q])

    def _second_centre(self, centre: np.ndarray) -> np.ndarray | None:
        """The best known point at least ``second_gap`` from ``centre`` (None: no such point, or ``second`` 0)."""
        if not self.s.second:
            return None
        best, out = -np.inf, None
        for theta, score, _y in self.t.points:
            if np.isfinite(score) and score > best and np.sqrt(((theta - centre) ** 2).sum()) >= self.s.second_gap:
                best, out = score, theta
        return None if out is None else np.asarray(out, float)

    def _candidates(self, centre: np.ndarray, th: np.ndarray, res: np.ndarray, h: float, radius: float,
                    evals: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Points around ``centre`` at every trust radius (uniform in the box, then around the best
        uniform ones) and their corrected fit, best first (``evals``: surrogate evaluations, default ``evals``)."""
        per = max(8, int(evals or self.s.evals) // (2 * len(self.s.scales)))
        beta = (_local_linear(th, res, centre, h, self.s.prior, self.s.ridge)
                if self.s.correct and self.s.linear and len(th) else None)
        xs, fits = [], []
        for scale in self.s.scales:
            r = min(scale * radius, 0.5)
            u = np.clip(centre + r * (2.0 * self.rng.random((per, self.d)) - 1.0), 0.0, 1.0)
            fu = self._fit(self.corrected(u, th, res, h, centre, beta))
            top = u[np.argsort(-fu, kind="stable")[:8]]
            v = np.clip(top[np.arange(per) % len(top)] + 0.25 * r * self.rng.standard_normal((per, self.d)), 0.0, 1.0)
            fv = self._fit(self.corrected(v, th, res, h, centre, beta))
            xs += [u, v]
            fits += [fu, fv]
        x, fit = np.vstack(xs), np.concatenate(fits)
        order = np.argsort(-fit, kind="stable")
        return x[order], fit[order]

    def tell(self, points: np.ndarray, ys: np.ndarray, scores: np.ndarray, before: float) -> None:
        """A batch is back (``before``: the best simulated score before it): move the trust radius."""
        best = float(np.max(scores)) if len(scores) else -np.inf
        if best > before + 1e-9:
            self.radius = min(self.radius * self.s.grow, self.s.radius_max)
        else:
            self.radius *= self.s.shrink
            if self.radius < self.s.radius_min:
                self.radius = self.s.radius0


def _local_linear(th: np.ndarray, res: np.ndarray, centre: np.ndarray, h: float, prior: float, ridge: float
                  ) -> np.ndarray:
    """(1 + d, M): the residual's kernel-weighted ridge fit ``a + ((theta - centre) / h) B`` (``prior``: weight of a
    zero residual at the centre; ``ridge``: of zero slopes)."""
    z = (th - centre) / h
    w = np.exp(-0.5 * (z * z).sum(1))
    x = np.hstack([np.ones((len(z), 1)), z])
    a = (x * w[:, None]).T @ x + np.diag([prior] + [ridge] * z.shape[1])
    return np.linalg.solve(a, (x * w[:, None]).T @ res)


def row_residuals(predict: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, y: np.ndarray,
                  chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """(theta, y - f(theta)) of stored rows, predicted in fixed chunks (computed once, shared by every target)."""
    theta = np.asarray(theta, float)
    pred = [np.asarray(predict(theta[i:i + chunk]), float) for i in range(0, len(theta), chunk)]
    return theta, np.asarray(y, float) - (np.vstack(pred) if pred else np.zeros_like(y))


def _nearest(rows: np.ndarray, centre: np.ndarray, k: int) -> np.ndarray:
    """The indices of the ``k`` rows nearest ``centre``, nearest first (ties: the lower index)."""
    from invphys.core.nearest import nearest_first

    return nearest_first(((rows - centre) ** 2).sum(1), k)


def _spread(pool: np.ndarray, fit: np.ndarray, k: int, gap: float, known: np.ndarray) -> list[np.ndarray]:
    """Up to ``k`` rows of ``pool`` (best first) at least ``gap`` from each other and from ``known``."""
    chosen: list[np.ndarray] = []
    if k <= 0:
        return chosen
    for lo in range(0, len(pool), 64):   # best first, a chunk at a time: most batches need the first chunk only
        part = pool[lo:lo + 64]
        ok = np.isfinite(fit[lo:lo + 64])
        if len(known):
            ok &= np.sqrt(((part[:, None, :] - known[None, :, :]) ** 2).sum(-1)).min(1) >= gap
        for x in part[ok]:
            if all(np.sqrt(((x - c) ** 2).sum()) >= gap for c in chosen):
                chosen.append(x)
                if len(chosen) == k:
                    return chosen
    return chosen
