"""Built-in optimizers plugins."""

from __future__ import annotations

OPTIMIZERS: list[type] = []
