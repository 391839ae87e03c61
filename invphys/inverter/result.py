"""What an inversion returns: candidates with parameters by name and unit, predictions and scores, and
how sure the answer is (:class:`~invphys.inverter.uncertainty.Uncertainty`: posterior draws and their
intervals, a lookup's neighbours, or none)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.inverter.uncertainty import Uncertainty, at_bound


@dataclass
class Candidate:
    """One answer: normalised ``theta``, physical ``params`` (space order), surrogate prediction and
    ensemble std, R_surr; after validation the simulated features, R_actual and the gap. A stored row of
    the bundle (a pool's neighbour) also carries its real features ``known`` and their R against the
    target ``r_known``: what the simulator gave there, no surrogate involved (zero spread)."""

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
    known: np.ndarray | None = None
    r_known: float | None = None

    @property
    def features(self) -> np.ndarray:
        """The features this candidate is best known by: its stored real features, else the prediction."""
        return self.predicted if self.known is None else self.known

    @property
    def spread(self) -> np.ndarray:
        """Their spread: 0 for stored real features, else the ensemble's std."""
        return np.asarray(self.std) if self.known is None else np.zeros_like(self.known)


@dataclass
class InversionResult:
    """The answer to one target, best candidate first.

    ``parameters``, ``theta``, ``predicted``, ``r_surrogate`` and ``uncertainty`` describe the best
    candidate; ``candidates`` holds all (``top_k``). Mappings are keyed by name in the bundle's order;
    parameters are in physical units (``units``), features in the features' units. ``polish``: what
    :meth:`~invphys.inverter.Inverter.polish` did (None when it did not run). ``parameter_uncertainty``: the
    posterior draws (``samples``, :meth:`interval`, ``identified``) or what the method has instead.
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
    parameter_uncertainty: Uncertainty = field(default_factory=Uncertainty)
    space: Any = None
    #: the bundle's failure model's probability that the best answer fails on the simulator (R_actual < 0.8;
    #: None without one: ``invphys diagnose --write --failures``)
    failure_score: float | None = None
    #: the observation noise the target gave (a std per feature, NaN where none; None: an exact target)
    target_std: np.ndarray | None = None
    #: the posterior's draws account for that noise (:mod:`~invphys.inverter.noise`)
    noise_posterior: bool = False

    @property
    def posterior(self) -> str:
        """"posterior" (draws from a posterior), "neighbours" (a lookup's nearest rows) or "none"."""
        return self.parameter_uncertainty.kind

    @property
    def samples(self) -> dict[str, np.ndarray] | None:
        """The draws (posterior, or a lookup's nearest rows) in physical units, ``{name: (S,)}``; None
        for a method that answers with a point."""
        u = self.parameter_uncertainty
        if not u.has_draws or u.draws is None:
            return None
        phys = self._physical(u.draws)
        return {n: phys[:, j] for j, n in enumerate(self.parameter_names)}

    def interval(self, level: float | None = None) -> dict[str, tuple[float, float, float]]:
        """Per parameter ``(low, median, high)`` in physical units: the central ``level`` interval
        (default: the level the answer was made with, 0.9 unless set). Raises for a point answer."""
        lo, med, hi = self.parameter_uncertainty.quantiles(level)
        q = self._physical(np.stack([lo, med, hi]))
        return {n: (float(q[0, j]), float(q[1, j]), float(q[2, j])) for j, n in enumerate(self.parameter_names)}

    @property
    def identified(self) -> dict[str, bool] | None:
        """Per parameter: pinned down by this target (see :mod:`~invphys.inverter.uncertainty`); None
        without a posterior."""
        ok = self.parameter_uncertainty.identified()
        return None if ok is None else dict(zip(self.parameter_names, map(bool, ok), strict=True))

    @property
    def at_bound(self) -> list[str]:
        """Parameters whose answer sits on a bound of the parameter box."""
        return [n for n, e in zip(self.parameter_names, at_bound(self.theta), strict=True) if e]

    def _physical(self, theta: np.ndarray) -> np.ndarray:
        if self.space is None:
            raise InvphysError("this result has no parameter space to convert draws to physical units")
        return np.asarray(self.space.denormalize(np.clip(theta, 0.0, 1.0)), dtype=np.float64)

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

    @property
    def r_known(self) -> float | None:
        """The best candidate's R from its stored real features (None unless it is a stored row)."""
        return self.best.r_known

    def spread(self) -> dict[str, float]:
        """Per parameter: range of the candidates' normalised values (wide = the target does not pin it)."""
        t = np.array([c.theta for c in self.candidates])
        return dict(zip(self.parameter_names, map(float, t.max(axis=0) - t.min(axis=0)), strict=True))

    def chi2(self, c: Candidate | None = None) -> float | None:
        """The noise-normalised misfit of a candidate (default: the best) over the given features:
        mean of (predicted - target)² / (std² + ensemble std²) (a stored row: its real features, no
        ensemble spread); about 1 when the answer fits the target as well as its noise allows, >> 1 when
        it does not. None for an exact target."""
        if self.target_std is None:
            return None
        c = c or self.best
        m = self.mask
        var = np.nan_to_num(self.target_std[m], nan=0.0) ** 2 + np.asarray(c.spread, dtype=np.float64)[m] ** 2
        r = np.asarray(c.features, dtype=np.float64)[m] - self.target[m]
        return float(np.mean(r * r / np.maximum(var, 1e-300)))

    def noise(self) -> dict[str, Any] | None:
        """What noise was assumed: per feature the std given (None: exact), whether the posterior used
        it, and the best answer's :meth:`chi2`; None for an exact target."""
        if self.target_std is None:
            return None
        std = {n: (_f(s) if g else None) for n, s, g in zip(self.feature_names, self.target_std, self.mask, strict=True)}
        return {"std": std, "model": "independent Gaussian per feature, variance std^2 + surrogate spread^2",
                "posterior": self.noise_posterior, "chi2": _f(self.chi2())}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: target, and per candidate the parameters (value, unit) and features side by side."""
        def candidate(rank: int, c: Candidate) -> dict[str, Any]:
            feats = {}
            for j, name in enumerate(self.feature_names):
                row: dict[str, Any] = {"target": _f(self.target[j]) if self.mask[j] else None,
                                       "predicted": _f(c.predicted[j]), "std": _f(c.std[j]),
                                       "unit": self.feature_units[j]}
                if self.target_std is not None and self.mask[j]:
                    row["target_std"] = _f(self.target_std[j])
                if c.known is not None:
                    row["known"] = _f(c.known[j])
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
            if c.known is not None:  # a stored row: its real features, simulated when the bundle was made
                out["r_known"] = _f(c.r_known)
            if self.target_std is not None:
                out["chi2"] = _f(self.chi2(c))
            if c.r_actual is not None or c.failure:
                out.update(r_actual=_f(c.r_actual), gap=_f(c.gap), failure=c.failure)
            return out

        data: dict[str, Any] = {
            "target": self.label, "method": self.method, "bundle_id": self.bundle_id,
            "partial": not bool(np.all(self.mask)),
            "evaluations": int(self.evaluations), "wall_time_s": round(float(self.wall_time_s), 6),
            "candidates": [candidate(i + 1, c) for i, c in enumerate(self.candidates)],
            "warnings": list(self.warnings), "failure_score": _f(self.failure_score)}
        data["noise"] = self.noise()
        if self.polish is not None:
            data["polish"] = {k: _f(v) if isinstance(v, float) else v for k, v in self.polish.items()}
        if len(self.candidates) > 1:
            data["spread"] = {k: _f(v) for k, v in self.spread().items()}
        data.update(self._uncertainty_dict())
        return data

    def _uncertainty_dict(self) -> dict[str, Any]:
        """``posterior`` (intervals, or None for a point answer), ``neighbours`` for a lookup, ``at_bound``."""
        u = self.parameter_uncertainty
        out: dict[str, Any] = {"posterior": None, "at_bound": self.at_bound}
        if not u.has_draws or u.draws is None:
            out["uncertainty"] = {"kind": u.kind, "note": u.note}
            return out
        iv, ident = self.interval(), self.identified
        params = {n: {"median": _f(m), "low": _f(lo), "high": _f(hi), "unit": unit,
                      **({} if ident is None else {"identified": ident[n]})}
                  for (n, (lo, m, hi)), unit in zip(iv.items(), self.parameter_units, strict=True)}
        block: dict[str, Any] = {"level": u.level, "draws": len(u.draws), "parameters": params}
        if u.kind == "posterior":
            block.update(outside_fraction=_f(u.outside_fraction), clipped=int(u.clipped), completions=u.completions,
                         recalibrated=u.recalibrated)
            out["posterior"] = block
        else:
            out[u.kind] = {**block, "note": u.note}
            out["uncertainty"] = {"kind": u.kind, "note": u.note}
        return out


def _f(v: Any) -> float | None:
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None
