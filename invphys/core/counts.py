"""Whole-number checks of user settings (counts, budgets, seeds): one rule, each caller its own message."""

from __future__ import annotations

from typing import Any

import numpy as np


def is_count(value: Any, low: int | None = 0, high: int | None = None) -> bool:
    """True for a whole number (a Python or NumPy integer, not a bool) in ``low .. high`` (None: no end)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        return False
    return bool((low is None or value >= low) and (high is None or value <= high))


__all__ = ["is_count"]
