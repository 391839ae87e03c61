"""The nearest-neighbour lookup baseline: answer with the parameters of the closest training row."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig
from invphys.plugins.baselines._base import PRIOR_STD, BaselineAnswers, DatasetBaseline, best_by_surrogate


class NearestNeighbour(DatasetBaseline):
    """Dataset lookup (docs/evaluation.md): no model, no simulation.

    ``metric``: ``r_gt`` ranks training rows by the recovery reward R_gt against the target (Euclidean
    distance on features divided by the scales s_k), ``standardised`` by Euclidean distance on z-scored
    features. With ``k`` > 1 the k nearest rows are candidates: ``select: nearest`` answers with the
    nearest, ``mean`` with their parameter mean, ``surrogate`` with the one the surrogate scores best
    (k surrogate evaluations). The k rows' parameter spread is reported for identifiability.
    """

    name: ClassVar[str] = "nearest_neighbour"

    class Config(PluginConfig):
        k: int = Field(1, ge=1, description="neighbours considered")
        metric: Literal["r_gt", "standardised"] = Field("r_gt", description="distance in feature space")
        select: Literal["nearest", "mean", "surrogate"] = Field("nearest", description="answer among the k")
        chunk: int = Field(4096, ge=1, description="targets per distance block (memory)")

    @property
    def evaluation_budget(self) -> int:
        return self.config.k if self.config.select == "surrogate" else 1

    def _fit(self, theta: np.ndarray, y: np.ndarray, scales: np.ndarray, progress: bool) -> dict[str, Any]:
        self._theta = theta
        self._scales = scales
        if self.config.metric == "r_gt":
            self._shift, self._div = np.zeros(y.shape[1]), np.maximum(scales, 1e-12)
        else:
            from invphys.core.objectives import feature_standardiser

            self._shift, self._div = feature_standardiser(y)
        self._z = (y - self._shift) / self._div
        return {"metric": self.config.metric, "k": self.config.k}

    def neighbours(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(indices (B, k), distances (B, k)) of the k nearest training rows, nearest first."""
        k = min(self.config.k, len(self._z))
        zt = (np.atleast_2d(targets) - self._shift) / self._div
        zt = np.where(np.isfinite(zt), zt, 0.0)
        idx, dist = [], []
        sq = (self._z ** 2).sum(axis=1)
        for s in range(0, len(zt), self.config.chunk):
            block = zt[s:s + self.config.chunk]
            d2 = np.maximum((block ** 2).sum(axis=1)[:, None] + sq[None, :] - 2.0 * block @ self._z.T, 0.0)
            part = np.argpartition(d2, k - 1, axis=1)[:, :k] if k < d2.shape[1] else np.tile(np.arange(d2.shape[1]), (len(block), 1))
            order = np.argsort(np.take_along_axis(d2, part, axis=1), axis=1)
            part = np.take_along_axis(part, order, axis=1)
            idx.append(part)
            dist.append(np.sqrt(np.take_along_axis(d2, part, axis=1)))
        return np.concatenate(idx), np.concatenate(dist)

    def _answer(self, targets: np.ndarray, predict_theta: Any) -> BaselineAnswers:
        idx, dist = self.neighbours(targets)
        cands = self._theta[idx]  # (B, k, d)
        b = len(targets)
        evals = np.zeros(b, dtype=np.int64)
        if self.config.select == "surrogate" and cands.shape[1] > 1:
            best, _ = best_by_surrogate(cands, targets, self._scales, predict_theta, self.penalty_fn)
            theta = cands[np.arange(b), best]
            evals[:] = cands.shape[1]
        elif self.config.select == "mean":
            theta = cands.mean(axis=1)
        else:
            theta = cands[:, 0]
        spread = cands.std(axis=1) / PRIOR_STD if cands.shape[1] > 1 else np.full(theta.shape, np.nan)
        return BaselineAnswers(theta=theta, candidates=cands, spread=spread, evaluations=evals, wall_time_s=0.0,
                               info={"rows": idx.tolist(), "distance": dist[:, 0].tolist()})

    def save(self, directory: str | Path) -> Path:
        """Write the lookup table (training parameters and scaled features) and the config."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(d / "nearest_neighbour.npz", theta=self._theta, z=self._z, shift=self._shift,
                            div=self._div, scales=self._scales)
        (d / "nearest_neighbour.json").write_text(json.dumps({"config": self.config.model_dump(),
                                                               "metrics": self.metrics}, indent=1))
        return d

    @classmethod
    def load(cls, directory: str | Path) -> NearestNeighbour:
        d = Path(directory)
        if not (d / "nearest_neighbour.npz").is_file():
            raise InvphysError(f"no saved nearest_neighbour baseline in {d}")
        meta = json.loads((d / "nearest_neighbour.json").read_text())
        plugin = cls(meta["config"])
        with np.load(d / "nearest_neighbour.npz") as f:
            plugin._theta, plugin._z, plugin._shift, plugin._div, plugin._scales = (
                f["theta"], f["z"], f["shift"], f["div"], f["scales"])
        plugin.metrics, plugin.fitted = meta["metrics"], True
        return plugin
