"""How sure an answer is: posterior draws and their intervals, or an honest spread, or none.

* ``posterior`` (a method with a trained posterior, e.g. sbi's NPE): draws from the posterior truncated
  to the parameter box; :meth:`Uncertainty.interval` gives the median and a central interval;
* ``neighbours`` (a lookup): the parameters of the :data:`NEIGHBOUR_ROWS` training rows nearest the
  target. A spread, not a posterior: it says how different the rows that look alike are;
* ``none`` (a policy or a search): a point answer; no interval is made up for it.

Identifiability: a parameter is ``identified`` when its central :data:`IDENTIFIED_LEVEL` interval spans
at most :data:`IDENTIFIED_WIDTH` of its normalised range. The prior U(0, 1) spans 0.9 at that level; a
posterior twice as narrow has ruled out at least half of the range. On the paper bundle's held-out rows
the four parameters the features do not pin (eta_s, r_s, eta_i, r_i) span about 0.75, the others well
under 0.5, so the threshold separates them with room on both sides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from invphys.core.errors import InvphysError

#: the level at which identifiability is judged (whatever level the user's intervals use)
IDENTIFIED_LEVEL = 0.9
#: widest central interval (fraction of the normalised range) of an identified parameter
IDENTIFIED_WIDTH = 0.5
#: rows a lookup's spread is made of
NEIGHBOUR_ROWS = 20
#: default interval level
DEFAULT_LEVEL = 0.9
#: distance from a bound, in the normalised range, at which an answer counts as on it
BOUND_TOL = 1e-9


def check_level(level: float) -> float:
    if isinstance(level, bool) or not isinstance(level, (int, float, np.floating)) or not 0 < float(level) < 1:
        raise InvphysError(f"interval level must be in (0, 1) (e.g. 0.9), got {level!r}")
    return float(level)


@dataclass
class Uncertainty:
    """``kind``: "posterior", "neighbours" or "none"; ``draws`` (S, d) in normalised units (None for
    "none"); ``level``: the default level of :meth:`interval`; ``outside_fraction``/``clipped``: the
    posterior's mass outside the box (rejected) and the draws clipped when rejection hit its cap."""

    kind: str = "none"
    draws: np.ndarray | None = None
    level: float = DEFAULT_LEVEL
    outside_fraction: float | None = None
    clipped: int = 0
    completions: int = 1
    note: str = ""
    #: the draws were corrected by the bundle's stored recalibration (``invphys diagnose --write``)
    recalibrated: bool = False

    @property
    def has_draws(self) -> bool:
        return self.draws is not None and len(self.draws) > 0

    def quantiles(self, level: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(low, median, high) per parameter (normalised) of the central ``level`` interval."""
        if not self.has_draws or self.draws is None:
            raise InvphysError(f"this answer has no draws to make an interval from (posterior: {self.kind})")
        lv = check_level(self.level if level is None else level)
        q = np.quantile(self.draws, [(1 - lv) / 2, 0.5, (1 + lv) / 2], axis=0)
        return q[0], q[1], q[2]

    def identified(self) -> np.ndarray | None:
        """Per parameter: its :data:`IDENTIFIED_LEVEL` interval spans at most :data:`IDENTIFIED_WIDTH`
        (None unless the draws are a posterior's)."""
        if self.kind != "posterior" or not self.has_draws:
            return None
        lo, _, hi = self.quantiles(IDENTIFIED_LEVEL)
        return np.asarray((hi - lo) <= IDENTIFIED_WIDTH)


def at_bound(theta: np.ndarray) -> np.ndarray:
    """Per parameter: the normalised value sits on 0 or 1."""
    t = np.asarray(theta, dtype=np.float64)
    return (t <= BOUND_TOL) | (t >= 1.0 - BOUND_TOL)


def answer_warnings(unc: Uncertainty, names: tuple[str, ...], theta: np.ndarray, mask: np.ndarray) -> list[str]:
    """What a user should know about one answer: unidentified parameters, a partial target that cannot
    pin every parameter, a posterior near the prior, clipped draws, values on a bound."""
    out: list[str] = []
    given, d = int(np.sum(mask)), len(names)
    if given < len(mask) and given < d:
        out.append(f"the target gives {given} features for {d} parameters: at most {given} can be pinned down")
    ident = unc.identified()
    if ident is not None and not ident.all():
        if not ident.any():
            out.append("the posterior stays near the prior: the target pins down none of the parameters")
        else:
            loose = ", ".join(n for n, ok in zip(names, ident, strict=True) if not ok)
            out.append(f"not identified by this target (90 % interval wider than {IDENTIFIED_WIDTH:g} of the "
                       f"range): {loose}")
    if unc.clipped:
        out.append(f"{unc.clipped} posterior draws were clipped to the parameter box: the posterior puts almost "
                   f"all its mass outside it ({unc.outside_fraction:.0%} of draws)")
    edge = at_bound(theta)
    if edge.any():
        out.append("the answer sits on a bound of the parameter box (the truth may lie beyond it): "
                   + ", ".join(f"{n} at its {'lower' if t <= 0.5 else 'upper'} bound"
                               for n, t, e in zip(names, theta, edge, strict=True) if e))
    return out
