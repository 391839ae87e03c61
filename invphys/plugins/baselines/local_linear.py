"""A local inverse from the data itself: a Gauss-Newton step from the lookup on real simulator outputs.

For a target y*, take the k training rows nearest in scaled feature space (as ``nearest_neighbour``
with ``metric: r_gt``), fit a ridge-regularised linear FORWARD model z ~ b + A (theta - theta_0) on
them (z = features / s_k; theta_0 the nearest row's parameters), and solve for the step that best
matches the target inside a trust region: ``||D^-1 (theta - theta_0)|| <= trust``, D the neighbours'
per-parameter standard deviation (a parameter the neighbours do not vary stays near the anchor). The
trust-region problem is solved Levenberg-Marquardt style (bisection on the damping). No global
surrogate, no simulation: one k x d least-squares fit and a few d x d solves per target (well under a
millisecond). With ``anchors`` > 1 the step is taken from each of the nearest ``anchors`` rows and the
candidate the local model predicts best is kept (no surrogate evaluations either).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig
from invphys.plugins.baselines._base import PRIOR_STD, BaselineAnswers, DatasetBaseline

KAPPA = 3.0  # the paper's R_gt sharpness (invphys.core.objectives.recovery_reward)


def local_fit(theta: np.ndarray, z: np.ndarray, centre: np.ndarray, weights: np.ndarray, ridge: float
              ) -> tuple[np.ndarray, np.ndarray]:
    """Weighted ridge fit ``z ~ b + A (theta - centre)`` on k rows; returns (b (M,), A (M, d)).

    The ridge acts on A only, in units of the parameters' normalised scale ([0, 1]).
    """
    k, d = theta.shape
    x = np.hstack([np.ones((k, 1)), theta - centre])
    sw = np.sqrt(weights)[:, None]
    xw, zw = x * sw, z * sw
    reg = np.diag(np.r_[0.0, np.full(d, ridge)])
    coef = np.linalg.solve(xw.T @ xw + reg + 1e-12 * np.eye(d + 1), xw.T @ zw)
    return coef[0], coef[1:].T


def trust_step(a: np.ndarray, r: np.ndarray, scale: np.ndarray, radius: float, iters: int = 40) -> np.ndarray:
    """argmin ||A s - r|| subject to ||s / scale|| <= radius (Levenberg-Marquardt damping by bisection)."""
    scale = np.maximum(scale, 1e-6)
    ap = a * scale[None, :]  # in u = s / scale
    g, h = ap.T @ r, ap.T @ ap
    d = len(scale)

    def solve(mu: float) -> np.ndarray:
        return np.linalg.solve(h + mu * np.eye(d), g)

    u = solve(1e-9 * (np.trace(h) / d + 1e-12))
    if radius <= 0:
        return np.zeros(d)
    if np.linalg.norm(u) <= radius:
        return u * scale
    lo, hi = 0.0, max(float(np.trace(h)), 1e-9)
    while np.linalg.norm(solve(hi)) > radius:
        hi *= 10.0
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        if np.linalg.norm(solve(mid)) > radius:
            lo = mid
        else:
            hi = mid
    return solve(hi) * scale


class LocalLinear(DatasetBaseline):
    """The lookup refined by a local linear forward model of the neighbours (docs/evaluation.md).

    ``k`` neighbours in feature space divided by the scales s_k; ``ridge`` on the local slopes;
    ``trust`` the step's radius in units of the neighbours' parameter spread; ``kernel``: ``uniform``
    weights or ``gaussian`` (bandwidth: the k-th neighbour's distance); ``anchors``: trust-region
    centres tried (the nearest rows), the answer the one whose local prediction scores best R_gt.
    """

    name: ClassVar[str] = "local_linear"

    class Config(PluginConfig):
        k: int = Field(40, ge=3, description="neighbours the local forward model is fitted on")
        ridge: float = Field(0.1, ge=0.0, description="ridge penalty on the local slopes")
        trust: float = Field(1.0, ge=0.0, description="step radius in units of the neighbours' parameter std")
        kernel: Literal["uniform", "gaussian"] = Field("uniform", description="neighbour weights")
        anchors: int = Field(1, ge=1, description="nearest rows tried as trust-region centres")
        base: Literal["anchor", "fit"] = Field("anchor", description="the step starts from the anchor row's real "
                                               "features (anchor) or from the local model's value there (fit)")

    @property
    def evaluation_budget(self) -> int:
        return 1

    def _fit(self, theta: np.ndarray, y: np.ndarray, scales: np.ndarray, progress: bool) -> dict[str, Any]:
        if len(theta) < 3:
            raise InvphysError(f"{self.name}: needs at least 3 training rows, got {len(theta)}")
        self._theta, self._scales = theta, scales
        self._z = y / np.maximum(scales, 1e-12)
        return {"k": min(self.config.k, len(theta)), "ridge": self.config.ridge, "trust": self.config.trust}

    def neighbours(self, targets: np.ndarray, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(indices (B, k), distances (B, k)) in scaled feature space, nearest first; ``exclude`` (B,) a row to skip each."""
        k = min(self.config.k, len(self._z) - (exclude is not None))
        zt = np.atleast_2d(targets) / np.maximum(self._scales, 1e-12)
        zt = np.where(np.isfinite(zt), zt, 0.0)
        d2 = np.maximum((zt ** 2).sum(1)[:, None] + (self._z ** 2).sum(1)[None, :] - 2.0 * zt @ self._z.T, 0.0)
        if exclude is not None:
            d2[np.arange(len(zt)), exclude] = np.inf
        part = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < d2.shape[1] else np.tile(np.arange(d2.shape[1]), (len(zt), 1))
        part = np.take_along_axis(part, np.argsort(np.take_along_axis(d2, part, axis=1), axis=1), axis=1)
        return part, np.sqrt(np.take_along_axis(d2, part, axis=1))

    def solve_one(self, z_target: np.ndarray, idx: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(answer (d,), candidates (anchors, d), local predicted R_gt of the answer) for one target."""
        cfg = self.config
        th, z = self._theta[idx], self._z[idx]
        if cfg.kernel == "gaussian":
            h = max(float(dist[-1]), 1e-12)
            w = np.exp(-0.5 * (dist / h) ** 2)
        else:
            w = np.ones(len(idx))
        w = w / w.sum()
        mean = w @ th
        spread = np.sqrt(np.maximum(w @ (th - mean) ** 2, 0.0))
        b, a = local_fit(th, z, mean, w, cfg.ridge)
        cands, preds = [], []
        for j in range(min(cfg.anchors, len(idx))):
            t0 = th[j]
            pred0 = z[j] if cfg.base == "anchor" else b + a @ (t0 - mean)
            step = trust_step(a, z_target - pred0, spread, cfg.trust)
            t = np.clip(t0 + step, 0.0, 1.0)
            pred = pred0 + a @ (t - t0)
            cands.append(t)
            preds.append(float(np.exp(-KAPPA * np.sqrt(np.mean((pred - z_target) ** 2)))))
        best = int(np.argmax(preds))
        return cands[best], np.array(cands), preds[best]

    def answer_rows(self, targets: np.ndarray, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(answers (B, d), candidates (B, anchors, d), local predicted R (B,), neighbour spread (B, d))."""
        idx, dist = self.neighbours(targets, exclude)
        zt = np.atleast_2d(targets) / np.maximum(self._scales, 1e-12)
        out, cands, pred = [], [], []
        for i in range(len(zt)):
            t, c, p = self.solve_one(zt[i], idx[i], dist[i])
            out.append(t)
            cands.append(c)
            pred.append(p)
        spread = self._theta[idx].std(axis=1) / PRIOR_STD
        return np.array(out), np.array(cands), np.array(pred), spread

    def _answer(self, targets: np.ndarray, predict_theta: Any) -> BaselineAnswers:
        theta, cands, pred, spread = self.answer_rows(targets)
        return BaselineAnswers(theta=theta, candidates=cands, spread=spread,
                               evaluations=np.zeros(len(targets), dtype=np.int64), wall_time_s=0.0,
                               info={"local_r": pred.tolist()})

    def save(self, directory: str | Path) -> Path:
        """Write the training rows (parameters, scaled features) and the config."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(d / "local_linear.npz", theta=self._theta, z=self._z, scales=self._scales)
        (d / "local_linear.json").write_text(json.dumps({"config": self.config.model_dump(),
                                                          "metrics": self.metrics}, indent=1))
        return d

    @classmethod
    def load(cls, directory: str | Path) -> LocalLinear:
        d = Path(directory)
        if not (d / "local_linear.npz").is_file():
            raise InvphysError(f"no saved local_linear baseline in {d}")
        meta = json.loads((d / "local_linear.json").read_text())
        plugin = cls(meta["config"])
        with np.load(d / "local_linear.npz") as f:
            plugin._theta, plugin._z, plugin._scales = f["theta"], f["z"], f["scales"]
        plugin.metrics, plugin.fitted = meta["metrics"], True
        return plugin
