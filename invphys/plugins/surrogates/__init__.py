"""Built-in surrogates plugins."""

from __future__ import annotations

SURROGATES: list[type] = []
