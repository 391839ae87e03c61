"""The invphys version (one place; the package root and the CLI read it from here)."""

from __future__ import annotations

__version__ = "0.1.0"
