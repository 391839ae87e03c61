"""Built-in executors plugins."""

from __future__ import annotations

EXECUTORS: list[type] = []
