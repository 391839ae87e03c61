"""The shipped bundles load against the installed simulator, and the docs' API example runs on one."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ("orange_peel_quick", "orange_peel_paper")


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_bundle_matches_the_installed_simulator(name) -> None:
    """Strict load: same simulator version and features as installed (else: retrain and re-export)."""
    import invphys

    inv = invphys.load_inverter(ROOT / "inverters" / name)
    assert inv.notes == []
    installed = inv.simulator().parameter_space()
    assert inv.parameter_space.describe() == installed.describe()  # names, ranges, units (E in Pa, ...)
    assert len(inv.parameter_names) == 9 and inv.parameter_space["E"].unit == "Pa"
    assert inv.default_method in inv.methods
    size = sum(p.stat().st_size for p in (ROOT / "inverters" / name).rglob("*") if p.is_file())
    assert size < 10e6, f"{name} is {size / 1e6:.1f} MB"


def test_docs_api_example_runs(monkeypatch, capsys) -> None:
    text = (ROOT / "docs" / "inverting.md").read_text()
    marker = "<!-- the block below runs in tests/test_inverter_docs.py -->"
    block = re.search(re.escape(marker) + r"\s*```python\n(.*?)```", text, re.S)
    assert block, "the API example block is missing from docs/inverting.md"
    monkeypatch.chdir(ROOT)
    exec(compile(block.group(1), "docs/inverting.md", "exec"), {})
    out = capsys.readouterr().out
    assert "R_surr" in out and "Pa" in out
