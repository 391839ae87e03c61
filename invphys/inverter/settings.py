"""Settings models shared by the Python API, the CLI and the pipeline: one model, one set of checks.

:class:`PolishSettings` is what :meth:`Inverter.polish <invphys.inverter.Inverter.polish>`,
``invphys invert --polish*`` and the active stage's ``active.polish`` passes are checked against.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError

#: polish's CMA-ES step in [0, 1]^d: the simulator is sharp in its parameters (orange peel, paper
#: preset: sigma0 0.05 improved 13 of 62 targets in its first generation; 0.012 improved 31 of 35 in
#: three generations, none got worse; docs/results.md)
POLISH_SIGMA0 = 0.012


class PolishSettings(BaseModel):
    """CMA-ES on the real simulator from validated answers (see :meth:`Inverter.polish`)."""

    model_config = ConfigDict(extra="forbid")

    budget: int = Field(24, ge=0, le=100_000, description="new simulator runs per polished target")
    popsize: int = Field(8, ge=2, le=10_000, description="points per CMA-ES generation")
    sigma0: float = Field(POLISH_SIGMA0, gt=0, le=10, allow_inf_nan=False,
                          description="CMA-ES step in the normalised [0, 1] parameter cube")
    below: float = Field(1.0, gt=0, le=1, allow_inf_nan=False,
                         description="polish only targets whose R_actual is below this")
    confirm: int = Field(0, ge=0, le=1000, description="re-runs per candidate after the polish (0: off)")
    confirm_candidates: int = Field(4, ge=1, le=1000, description="candidates per target that confirm re-runs")

    @field_validator("budget", "popsize", "confirm", "confirm_candidates", mode="before")
    @classmethod
    def _whole(cls, value: Any) -> Any:
        if not is_count(value, None):
            raise ValueError("must be a whole number")
        return int(value)

    @classmethod
    def checked(cls, names: dict[str, str] | None = None, **values: Any) -> PolishSettings:
        """The settings from ``values`` (None values: the default), or one :class:`InvphysError` line;
        ``names`` maps fields to the names the user wrote (e.g. ``{"sigma0": "--polish-sigma"}``)."""
        try:
            return cls(**{k: v for k, v in values.items() if v is not None})
        except ValidationError as exc:
            err = exc.errors()[0]
            field = str(err["loc"][0]) if err["loc"] else ""
            name = (names or {}).get(field, f"polish {field}")
            desc = cls.model_fields[field].description if field in cls.model_fields else ""
            raise InvphysError(f"{name} must be {_rule(field, err)} ({desc}), got {err.get('input')!r}") from None


def _rule(field: str, err: Any) -> str:
    """The broken rule of a field in words (``>= 0``, ``in (0, 1]``, ``a whole number``)."""
    if field == "below":
        return "in (0, 1]"
    ctx = err.get("ctx") or {}
    for key, sign in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<")):
        if key in ctx:
            return f"{sign} {ctx[key]}"
    return "a finite number" if err.get("type") == "finite_number" else "a whole number"


def check_polish(budget: int, popsize: int, sigma0: float, below: float, confirm: int = 0,
                 confirm_candidates: int = 4) -> None:
    """Raise :class:`InvphysError` for polish settings that cannot run (:class:`PolishSettings`)."""
    PolishSettings.checked(budget=budget, popsize=popsize, sigma0=sigma0, below=below, confirm=confirm,
                           confirm_candidates=confirm_candidates)
