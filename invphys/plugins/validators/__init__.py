"""Built-in validator plugins (paper sec. 3.6)."""

from __future__ import annotations

from invphys.plugins.validators.simulator import SimulatorValidator

VALIDATORS: list[type] = [SimulatorValidator]

__all__ = ["VALIDATORS", "SimulatorValidator"]
