"""Shared fixtures. Tests run on CPU, with tiny presets and small data.

These are the framework's tests (a toy simulator where any simulator serves); an example's own tests live in
its folder: examples/anisompm/tests (the engine), examples/orange_peel/tests, examples/cheese_cut/tests.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
os.environ.setdefault("MPLBACKEND", "Agg")
# tests/ importable as a package root for helper modules (e.g. spawn workers importing test plugins)
if str(ROOT / "tests") not in sys.path:
    sys.path.insert(0, str(ROOT / "tests"))


@pytest.fixture
def fresh_registry():
    """A registry with built-ins only (no entry points), independent of the process-wide one."""
    from invphys.registry import Registry

    return Registry(autoload=False)
