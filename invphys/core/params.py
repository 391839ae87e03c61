"""Parameter spaces: names, physical ranges and the log-scale normalisation to [0, 1].

A :class:`ParameterSpace` maps physical parameter vectors (in the units the simulator uses) to the
unit hypercube that samplers, surrogates and optimisers work in, as in the paper's Table 1: a
parameter marked ``log`` is normalised as ``(log x - log lo) / (log hi - log lo)``, any other as
``(x - lo) / (hi - lo)``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from invphys.core.errors import ParameterRangeError


@dataclass(frozen=True)
class Parameter:
    """One scalar parameter: its name, physical range ``[low, high]`` and scaling."""

    name: str
    low: float
    high: float
    log: bool = False
    unit: str = ""
    description: str = ""

    def __post_init__(self) -> None:
        if not self.low < self.high:
            raise ValueError(f"parameter {self.name!r}: low ({self.low}) must be < high ({self.high})")
        if self.log and self.low <= 0:
            raise ValueError(f"parameter {self.name!r}: a log-scale range must be positive")

    def range_text(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        return f"[{format_value(self.low)}, {format_value(self.high)}]{unit}"


@dataclass(frozen=True)
class ParameterSpace:
    """An ordered set of :class:`Parameter` with vectorised normalise/denormalise."""

    parameters: tuple[Parameter, ...]
    _index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        names = [p.name for p in self.parameters]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"duplicate parameter names: {dupes}")
        object.__setattr__(self, "_index", {n: i for i, n in enumerate(names)})

    # -- description -------------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def dim(self) -> int:
        return len(self.parameters)

    def __len__(self) -> int:
        return self.dim

    def __getitem__(self, name: str) -> Parameter:
        return self.parameters[self._index[name]]

    @property
    def _lo(self) -> np.ndarray:
        return np.array([np.log(p.low) if p.log else p.low for p in self.parameters])

    @property
    def _hi(self) -> np.ndarray:
        return np.array([np.log(p.high) if p.log else p.high for p in self.parameters])

    @property
    def _logmask(self) -> np.ndarray:
        return np.array([p.log for p in self.parameters])

    # -- checks --------------------------------------------------------------------------------
    def check(self, physical: np.ndarray | Sequence[float], rtol: float = 1e-9) -> np.ndarray:
        """Return ``physical`` as a float array of shape (..., dim), or raise naming every offender.

        Raises :class:`ParameterRangeError` naming each parameter outside its range (or not finite),
        with the first offending value as given, e.g.
        ``E = 9000 is outside its range [50, 8000] Pa; sigma_s = 0.0499 is outside its range [0.05, 0.5]``.
        """
        try:
            x = np.asarray(physical, dtype=np.float64)
        except (TypeError, ValueError):
            raise ParameterRangeError(f"parameters must be numbers, got {_shown(physical)}") from None
        if x.shape[-1:] != (self.dim,):
            raise ParameterRangeError(
                f"expected {self.dim} parameters ({', '.join(self.names)}), got shape {x.shape}"
            )
        flat = x.reshape(-1, self.dim)
        problems = []
        for j, p in enumerate(self.parameters):
            col = flat[:, j]
            span = (p.high - p.low) * rtol
            bad = ~np.isfinite(col) | (col < p.low - span) | (col > p.high + span)
            if bad.any():
                value = col[np.argmax(bad)]
                what = "is not a finite number" if not np.isfinite(value) else f"is outside its range {p.range_text()}"
                rows = int(bad.sum())
                more = f" ({rows} rows)" if flat.shape[0] > 1 and rows > 1 else ""
                problems.append(f"{p.name} = {format_value(value)} {what}{more}")
        if problems:
            raise ParameterRangeError("; ".join(problems))
        return np.clip(x, [p.low for p in self.parameters], [p.high for p in self.parameters])

    def check_unit(self, unit: np.ndarray | Sequence[float]) -> np.ndarray:
        """Return ``unit`` as an array, raising if any coordinate is outside [0, 1] or not finite."""
        u = np.asarray(unit, dtype=np.float64)
        if u.shape[-1:] != (self.dim,):
            raise ParameterRangeError(f"expected {self.dim} normalised parameters, got shape {u.shape}")
        flat = u.reshape(-1, self.dim)
        bad = ~np.isfinite(flat) | (flat < -1e-9) | (flat > 1 + 1e-9)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise ParameterRangeError(
                f"normalised {self.names[col]} = {format_value(flat[row, col])} is outside [0, 1]"
            )
        return np.clip(u, 0.0, 1.0)

    # -- mapping -------------------------------------------------------------------------------
    def normalize(self, physical: np.ndarray | Sequence[float]) -> np.ndarray:
        """Physical values (..., dim) -> unit hypercube (..., dim). Checks ranges first."""
        x = self.check(physical)
        t = np.where(self._logmask, np.log(np.maximum(x, 1e-300)), x)
        return np.clip((t - self._lo) / (self._hi - self._lo), 0.0, 1.0)

    def denormalize(self, unit: np.ndarray | Sequence[float]) -> np.ndarray:
        """Unit hypercube (..., dim) -> physical values (..., dim). Checks [0, 1] first."""
        u = self.check_unit(unit)
        t = self._lo + u * (self._hi - self._lo)
        x = np.where(self._logmask, np.exp(t), t)
        # exact endpoints despite exp/log round-off
        return np.clip(x, [p.low for p in self.parameters], [p.high for p in self.parameters])

    def from_mapping(self, values: Mapping[str, float], defaults: Mapping[str, float] | None = None) -> np.ndarray:
        """A physical vector from a ``{name: value}`` mapping; unknown names and gaps are errors.

        Missing names take ``defaults`` (physical) when given, else raise.
        """
        unknown = sorted(set(values) - set(self.names))
        if unknown:
            from invphys.core.errors import did_you_mean

            hints = "; ".join(f"{u!r}{did_you_mean(u, self.names)}" for u in unknown)
            raise ParameterRangeError(f"unknown parameter(s): {hints}. Known: {', '.join(self.names)}")
        merged = dict(defaults or {})
        merged.update(values)
        missing = [n for n in self.names if n not in merged]
        if missing:
            raise ParameterRangeError(f"missing parameter(s): {', '.join(missing)}")
        not_numbers = [f"{n} = {_shown(merged[n])} is not a number" for n in self.names
                       if not _is_number(merged[n])]
        if not_numbers:
            raise ParameterRangeError("; ".join(not_numbers))
        return self.check([float(merged[n]) for n in self.names])

    def to_mapping(self, physical: np.ndarray | Sequence[float]) -> dict[str, float]:
        """A ``{name: value}`` dict from one physical vector."""
        x = np.asarray(physical, dtype=np.float64).reshape(self.dim)
        return {n: float(v) for n, v in zip(self.names, x, strict=True)}

    def center(self) -> np.ndarray:
        """The physical point at the centre of the unit hypercube."""
        return self.denormalize(np.full(self.dim, 0.5))

    def describe(self) -> list[dict[str, object]]:
        """One JSON-ready row per parameter (for docs, reports and ``--json`` output)."""
        return [
            {"name": p.name, "low": p.low, "high": p.high, "log": p.log, "unit": p.unit,
             "description": p.description}
            for p in self.parameters
        ]


def format_value(value: float) -> str:
    """A number as given: integers without a point, other floats in their shortest exact form
    (``0.049999`` stays ``0.049999``; never rounded onto a bound as ``%g`` would)."""
    v = float(value)
    if not np.isfinite(v):
        return str(v)
    if v.is_integer() and abs(v) < 1e16:
        return str(int(v))
    return repr(v)


def _is_number(value: object) -> bool:
    import numbers

    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."
