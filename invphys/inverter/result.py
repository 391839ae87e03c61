"""What an inversion returns: candidates with parameters by name and unit, predictions and scores."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Candidate:
    """One answer: normalised ``theta``, physical ``params`` (space order), surrogate prediction and
    ensemble std, R_surr; after validation the simulated features, R_actual and the gap."""

    theta: np.ndarray
    params: np.ndarray
    predicted: np.ndarray
    std: np.ndarray
    r_surrogate: float
    source: str = ""
    actual: np.ndarray | None = None
    r_actual: float | None = None
    gap: float | None = None
    failure: str | None = None


@dataclass
class InversionResult:
    """The answer to one target, best candidate first.

    ``parameters``, ``theta``, ``predicted``, ``r_surrogate`` and ``uncertainty`` describe the best
    candidate; ``candidates`` holds all (``top_k``). Mappings are keyed by name in the bundle's order;
    parameters are in physical units (``units``), features in the features' units. ``polish``: what
    :meth:`~invphys.inverter.Inverter.polish` did (None when it did not run).
    """

    label: str
    method: str
    target: np.ndarray
    mask: np.ndarray
    candidates: list[Candidate]
    parameter_names: tuple[str, ...]
    parameter_units: tuple[str, ...]
    feature_names: tuple[str, ...]
    feature_units: tuple[str, ...]
    evaluations: int = 0
    wall_time_s: float = 0.0
    warnings: list[str] = field(default_factory=list)
    bundle_id: str = ""
    polish: dict[str, Any] | None = None

    @property
    def best(self) -> Candidate:
        return self.candidates[0]

    @property
    def parameters(self) -> dict[str, float]:
        """Best candidate's physical parameters, ``{name: value}`` in the space's order."""
        return dict(zip(self.parameter_names, map(float, self.best.params), strict=True))

    @property
    def theta(self) -> np.ndarray:
        """Best candidate's normalised parameters in [0, 1]^d."""
        return self.best.theta

    @property
    def predicted(self) -> dict[str, float]:
        """Surrogate-predicted features of the best candidate, by name."""
        return dict(zip(self.feature_names, map(float, self.best.predicted), strict=True))

    @property
    def uncertainty(self) -> dict[str, float]:
        """Surrogate ensemble std per feature at the best candidate (0 for a single network)."""
        return dict(zip(self.feature_names, map(float, self.best.std), strict=True))

    @property
    def r_surrogate(self) -> float:
        return float(self.best.r_surrogate)

    @property
    def r_actual(self) -> float | None:
        return self.best.r_actual

    def spread(self) -> dict[str, float]:
        """Per parameter: range of the candidates' normalised values (wide = the target does not pin it)."""
        t = np.array([c.theta for c in self.candidates])
        return dict(zip(self.parameter_names, map(float, t.max(axis=0) - t.min(axis=0)), strict=True))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: target, and per candidate the parameters (value, unit) and features side by side."""
        def candidate(rank: int, c: Candidate) -> dict[str, Any]:
            feats = {}
            for j, name in enumerate(self.feature_names):
                row: dict[str, Any] = {"target": _f(self.target[j]) if self.mask[j] else None,
                                       "predicted": _f(c.predicted[j]), "std": _f(c.std[j]),
                                       "unit": self.feature_units[j]}
                if c.actual is not None:
                    row["actual"] = _f(c.actual[j])
                if not self.mask[j]:
                    row["used"] = False
                feats[name] = row
            out: dict[str, Any] = {
                "rank": rank, "source": c.source,
                "parameters": {n: {"value": _f(v), "unit": u} for n, v, u in
                               zip(self.parameter_names, c.params, self.parameter_units, strict=True)},
                "theta": [_f(v) for v in c.theta], "r_surrogate": _f(c.r_surrogate), "features": feats}
            if c.r_actual is not None or c.failure:
                out.update(r_actual=_f(c.r_actual), gap=_f(c.gap), failure=c.failure)
            return out

        data: dict[str, Any] = {
            "target": self.label, "method": self.method, "bundle_id": self.bundle_id,
            "partial": not bool(np.all(self.mask)),
            "evaluations": int(self.evaluations), "wall_time_s": round(float(self.wall_time_s), 6),
            "candidates": [candidate(i + 1, c) for i, c in enumerate(self.candidates)],
            "warnings": list(self.warnings)}
        if self.polish is not None:
            data["polish"] = {k: _f(v) if isinstance(v, float) else v for k, v in self.polish.items()}
        if len(self.candidates) > 1:
            data["spread"] = {k: _f(v) for k, v in self.spread().items()}
        return data


def _f(v: Any) -> float | None:
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None
