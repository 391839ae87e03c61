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


@pytest.mark.parametrize("name", [*SHIPPED, "cheese_cut_quick"])
def test_shipped_bundle_feature_units_match_the_extractor(name) -> None:
    """The bundle records the installed extractor's feature units (empty ones too); a stale bundle fails."""
    import invphys
    from invphys.inverter.writer import feature_units as _units

    inv = invphys.load_inverter(ROOT / "inverters" / name)
    ext = inv.extractor(inv.simulator())
    assert list(inv.bundle.feature_units) == _units(ext, list(inv.feature_names))


def test_feature_units_reach_the_cli_output() -> None:
    import json

    from typer.testing import CliRunner

    import invphys
    from invphys.cli import app

    bundle = ROOT / "inverters" / "cheese_cut_quick"
    inv = invphys.load_inverter(bundle)
    _, y = inv.bundle.data("test")
    items = [a for n, v in zip(inv.feature_names, y[0], strict=True) for a in ("--feature", f"{n}={v}")]
    res = CliRunner().invoke(app, ["invert", str(bundle), *items, "--json"])
    assert res.exit_code == 0, res.output
    feats = json.loads(res.stdout)["results"][0]["candidates"][0]["features"]
    units = dict(zip(inv.feature_names, inv.bundle.feature_units, strict=True))
    assert units["peak_force"] == "N" and all(feats[n]["unit"] == u for n, u in units.items())
    text = CliRunner().invoke(app, ["invert", str(bundle), *items]).output
    assert re.search(r"peak_force\s.*\sN\s", text), text
