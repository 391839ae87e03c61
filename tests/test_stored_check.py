"""invphys diagnose --check-stored: the stored recalibration measured on held-out rows the stored
diagnosis did not use (tiny trained toy bundle)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from test_inverter_support import diagnose_app, npe_toy_bundle

from invphys.core.errors import InvphysError


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A dataset + train + invert run of the toy oscillator with a small NPE (~80 held-out rows)."""
    pytest.importorskip("sbi")
    return npe_toy_bundle(tmp_path_factory.mktemp("check") / "run", "check-toy", seed=7, max_epochs=20,
                          test_fraction=0.4)


def _cli():
    return diagnose_app()


def test_a_bundle_without_stored_diagnostics_gets_one_error_line(bundle, tmp_path) -> None:
    from typer.testing import CliRunner

    assert not (bundle / "diagnostics").exists()
    res = CliRunner().invoke(_cli(), ["diagnose", str(bundle), "--check-stored", "--out", str(tmp_path / "c")])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert lines[0].startswith("error:") and "no stored diagnostics" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "c").exists()


def test_the_check_uses_only_unused_rows_and_gives_the_same_numbers_twice(bundle) -> None:
    from invphys.core.dataset import keys_fingerprint
    from invphys.evaluation import stored_check as sc
    from invphys.evaluation.diagnose import diagnose
    from invphys.evaluation.diagnose_report import write_into_bundle
    from invphys.evaluation.heldout import heldout_rows
    from invphys.inverter import load_inverter

    inv = load_inverter(bundle)
    held = heldout_rows(inv.bundle)
    assert len(held) >= 70  # 80 test rows less the simulator's failures
    write_into_bundle(diagnose(inv, rows=30, draws=30), bundle)  # the first 30 by key, recorded by key
    used = json.loads((bundle / "diagnostics" / sc.ROWS_USED_FILE).read_text())["keys"]
    assert sorted(used) == sorted(held.keys[:30].tolist())
    inv = load_inverter(bundle)
    check, rebuilt = sc.check_stored(inv, draws=30)
    assert rebuilt is None and check["rows"]["n"] == len(held) - 30 and check["rows"]["used_by_stored_diagnosis"] == 30
    assert check["rows"]["keys_fingerprint"] == keys_fingerprint(held.keys[30:].tolist())  # exactly the others
    assert set(check["after"]["coverage"]) == {"0.5", "0.8", "0.9", "0.95"}
    assert check["after"]["tarp"]["n_refs"] == 20 and len(check["after"]["sbc"]["ks_pvalue"]) == inv.bundle.space.dim
    again, _ = sc.check_stored(load_inverter(bundle), draws=30)
    assert {k: v for k, v in again.items() if k != "created_utc"} == {k: v for k, v in check.items() if k != "created_utc"}
    part, _ = sc.check_stored(inv, draws=30, rows=20)  # --rows: the first unused rows by key
    assert part["rows"]["keys_fingerprint"] == keys_fingerprint(held.keys[30:50].tolist())
    # the check names the stored block it applied
    assert check["checked"] == sc.recalibration_digest(json.loads((bundle / "diagnostics" / "calibration.json").read_text()))


def test_diagnostics_written_before_the_keys_were_recorded_are_rebuilt_from_the_report(bundle, tmp_path) -> None:
    from invphys.evaluation import stored_check as sc
    from invphys.evaluation.heldout import heldout_rows
    from invphys.inverter.bundle import Bundle

    old = tmp_path / "old"
    shutil.copytree(bundle, old)
    (old / "diagnostics" / sc.ROWS_USED_FILE).unlink()
    b = Bundle(old, verify=False)
    report = json.loads((old / "diagnostics" / "report.json").read_text())
    keys, how = sc.used_keys(b, report)
    assert keys == set(heldout_rows(b).keys[:30].tolist()) and "rebuilt" in how
    report["heldout"]["rows"] += 1  # the stores no longer give what the report recorded: refused, not guessed
    with pytest.raises(InvphysError, match="cannot be told apart"):
        sc.used_keys(b, report)


def test_check_stored_writes_json_and_markdown_and_adds_a_block_to_the_bundle(bundle, tmp_path) -> None:
    from typer.testing import CliRunner

    from invphys.inverter.bundle import Bundle

    out = tmp_path / "check"
    res = CliRunner().invoke(_cli(), ["diagnose", str(bundle), "--check-stored", "--draws", "30", "--out", str(out),
                                      "--write", "--json"])
    assert res.exit_code == 0, res.output
    shown = json.loads(res.stdout)
    stored = json.loads((out / "check_unused_rows.json").read_text())
    from invphys.evaluation.heldout import heldout_rows

    assert shown["rows"]["n"] == stored["rows"]["n"] == len(heldout_rows(Bundle(bundle))) - 30
    assert "| joint (TARP, 20 references) |" in (out / "check_unused_rows.md").read_text()
    report = json.loads((bundle / "diagnostics" / "report.json").read_text())
    assert report["check_unused_rows"]["rows"] == stored["rows"]
    assert "Check on unused rows" in (bundle / "README.md").read_text()
    assert "Check on unused rows" in (bundle / "diagnostics" / "summary.md").read_text()
    assert "diagnostics/check_unused_rows.json" in Bundle(bundle).manifest["files"]  # re-hashed: verifies
    bad = CliRunner().invoke(_cli(), ["diagnose", str(bundle), "--check-stored", "--method", "x", "--write"])
    assert bad.exit_code == 2 and "do not apply" in bad.output
    assert np.isfinite(stored["clipped_share"])
