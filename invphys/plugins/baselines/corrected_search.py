"""Best of a few local candidates, scored by the surrogate corrected with the neighbours' real residuals.

The global surrogate f is biased where the target lies (it scores the true parameters of held-out
targets far below the simulator). The training rows nearest the target carry the bias itself: their
real features y_j minus f(theta_j). This method scores candidates with the corrected predictor

    y(theta) = f(theta) + sum_j w_j(theta) (y_j - f(theta_j)),   w_j ~ exp(-|theta - theta_j|^2 / 2 h^2)

over the ``neighbours`` nearest rows (in scaled feature space), so near the data it reproduces the
real outputs and between the rows it keeps the surrogate's shape. Candidates: the neighbour rows
themselves (scored by their real features, no evaluation), the trust-region steps of
:class:`~invphys.plugins.baselines.local_linear.LocalLinear` from the nearest ``anchors`` rows, and
Gaussian perturbations around those anchors (scale: the neighbours' parameter spread). Surrogate
evaluations per target: ``neighbours`` + the candidates (``budget`` in all). Each target's perturbations
come from a stream of its own, seeded from ``seed`` and the target's values
(:func:`~invphys.evaluators.simulator_loop.row_seed`), so an answer does not depend on the target's
position or on the other targets of the batch.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.objectives import recovery_reward
from invphys.plugins.baselines._base import PRIOR_STD, BaselineAnswers
from invphys.plugins.baselines.local_linear import LocalLinear


class CorrectedSearch(LocalLinear):
    """Local candidates scored by the residual-corrected surrogate (needs ``predict_theta``).

    Inherits the lookup and the local linear step (``k``, ``ridge``, ``kernel``) from ``local_linear``.
    """

    name: ClassVar[str] = "corrected_search"
    #: "2": perturbations seeded per target (before: one stream for the whole batch); stage keys and the
    #: baselines' answer cache record it, so answers made under the old streams are not served again
    version: ClassVar[str] = "2"

    class Config(LocalLinear.Config):
        neighbours: int = Field(8, ge=1, description="rows whose residuals correct the surrogate")
        anchors: int = Field(4, ge=1, description="nearest rows the candidates start from")
        trusts: list[float] = Field([1.0, 2.0, 4.0], description="local-linear step radii tried from each anchor")
        budget: int = Field(64, ge=2, description="surrogate evaluations per target, neighbours included")
        bandwidth: float = Field(0.2, gt=0.0, description="residual kernel width h in normalised parameters")
        seed: int = Field(0, description="seed of the perturbations")

    @property
    def evaluation_budget(self) -> int:
        return self.config.budget

    def _fit(self, theta: np.ndarray, y: np.ndarray, scales: np.ndarray, progress: bool) -> dict[str, Any]:
        cfg = self.config
        n_steps = cfg.anchors * len(cfg.trusts)
        if cfg.neighbours + n_steps >= cfg.budget:
            raise InvphysError(f"{self.name}: budget {cfg.budget} leaves no room after {cfg.neighbours} neighbours "
                               f"and {n_steps} local steps")
        return {**super()._fit(theta, y, scales, progress), "budget": cfg.budget, "neighbours": cfg.neighbours}

    def _candidates(self, z_target: np.ndarray, idx: np.ndarray, dist: np.ndarray, rng: np.random.Generator
                    ) -> np.ndarray:
        """Local-linear steps and perturbations around the nearest ``anchors`` rows, (n, d) in [0, 1]."""
        cfg = self.config
        th, z = self._theta[idx], self._z[idx]
        w = np.exp(-0.5 * (dist / max(float(dist[-1]), 1e-12)) ** 2) if cfg.kernel == "gaussian" else np.ones(len(idx))
        w = w / w.sum()
        mean = w @ th
        spread = np.maximum(np.sqrt(np.maximum(w @ (th - mean) ** 2, 0.0)), 1e-3)
        from invphys.plugins.baselines.local_linear import local_fit, trust_step

        _, a = local_fit(th, z, mean, w, cfg.ridge)
        anchors = min(cfg.anchors, len(idx))
        out = [np.clip(th[j] + trust_step(a, z_target - z[j], spread, t), 0.0, 1.0)
               for j in range(anchors) for t in cfg.trusts]
        n_rand = cfg.budget - cfg.neighbours - len(out)
        which = rng.integers(0, anchors, n_rand)
        radius = rng.choice([0.5, 1.0, 2.0], n_rand)
        out += list(np.clip(th[which] + rng.standard_normal((n_rand, th.shape[1])) * spread * radius[:, None], 0.0, 1.0))
        return np.array(out)

    def _answer(self, targets: np.ndarray, predict_theta: Any) -> BaselineAnswers:
        if predict_theta is None:
            raise InvphysError(f"{self.name} scores candidates with the surrogate: it needs predict_theta")
        from invphys.evaluators.simulator_loop import row_seed

        cfg = self.config
        idx, dist = self.neighbours(targets)
        zt = targets / np.maximum(self._scales, 1e-12)
        nb = min(cfg.neighbours, idx.shape[1])
        rngs = [np.random.default_rng(row_seed(cfg.seed, target, "corrected_search")) for target in targets]
        cands = np.array([self._candidates(zt[i], idx[i], dist[i], rngs[i]) for i in range(len(targets))])  # (B, n, d)
        b, n, d = cands.shape
        rows = idx[:, :nb]
        # one surrogate call for every target's neighbours and candidates
        pts = np.concatenate([self._theta[rows].reshape(b * nb, d), cands.reshape(b * n, d)])
        pred = np.asarray(predict_theta(pts), dtype=np.float64) / np.maximum(self._scales, 1e-12)
        f_rows, f_c = pred[:b * nb].reshape(b, nb, -1), pred[b * nb:].reshape(b, n, -1)
        resid = self._z[rows] - f_rows  # (B, nb, M)
        d2 = ((cands[:, :, None, :] - self._theta[rows][:, None, :, :]) ** 2).sum(-1)  # (B, n, nb)
        w = np.exp(-0.5 * d2 / cfg.bandwidth ** 2) + 1e-300
        w = w / w.sum(-1, keepdims=True)
        corrected = f_c + np.einsum("bnk,bkm->bnm", w, resid)
        ones = np.ones(len(self._scales))
        score_c = recovery_reward(corrected, zt[:, None, :], ones)  # (B, n)
        score_rows = recovery_reward(self._z[rows], zt[:, None, :], ones)  # (B, nb): real features
        allc = np.concatenate([self._theta[rows], cands], axis=1)
        scores = np.concatenate([score_rows, score_c], axis=1)
        best = np.argmax(scores, axis=1)
        theta = allc[np.arange(b), best]
        spread = self._theta[idx].std(axis=1) / PRIOR_STD
        return BaselineAnswers(theta=theta, candidates=allc, spread=spread,
                               evaluations=np.full(b, nb + n, dtype=np.int64), wall_time_s=0.0,
                               info={"corrected_r": scores[np.arange(b), best].tolist(),
                                     "chose_row": (best < nb).tolist()})
