"""Built-in validators plugins."""

from __future__ import annotations

VALIDATORS: list[type] = []
