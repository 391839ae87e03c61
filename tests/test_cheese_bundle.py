"""The shipped cheese-cut bundle: it loads, carries the methods that win on cheese-cut targets (a fitted
NPE best of 64 as the default, the lookup, CMA-ES), answers deterministically, carries its diagnostics, and
`invphys invert` answers with it from the command line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("sbi")

ROOT = Path(__file__).resolve().parent.parent
BUNDLE = ROOT / "inverters" / "cheese_cut_quick"


@pytest.fixture(scope="module")
def inv():
    import invphys

    return invphys.load_inverter(BUNDLE)


def _target(inv, row: int = 0) -> dict[str, float]:
    _, y = inv.bundle.data("test")
    return dict(zip(inv.feature_names, y[row].tolist(), strict=True))


def test_the_bundle_loads_with_a_fitted_npe_as_its_default(inv) -> None:
    manifest = yaml.safe_load((BUNDLE / "manifest.yaml").read_text())
    assert manifest["format_version"] == 2 and inv.notes == []
    assert inv.default_method == "npe_best64"
    assert {"npe_best64", "lookup", "cma_es_540"} <= set(inv.methods)
    npe = manifest["methods"]["npe_best64"]
    assert npe["type"] == "npe" and npe["config"]["answer"] == "best_surrogate" and npe["config"]["samples"] == 64
    assert npe["path"] and (BUNDLE / npe["path"] / "npe_weights.npz").is_file()
    assert not list(BUNDLE.rglob("*.pkl")) and not list(BUNDLE.rglob("npe.pt")), "format 2 holds no pickles"
    assert inv.bundle.manifest["dataset"]["n_train"] == 1600


def test_the_default_answers_a_target_deterministically(inv) -> None:
    import invphys

    t = _target(inv)
    first = inv.invert(t)
    assert first.method == "npe_best64" and first.posterior == "posterior"
    again = invphys.load_inverter(BUNDLE).invert(t)
    assert first.parameters == again.parameters
    many = inv.invert_many([_target(inv, 5), t])
    assert many[1].parameters == first.parameters, "an answer must not depend on the other targets"
    truth = inv.bundle.data("test")[0][0]
    assert np.abs(first.theta - truth)[[0, 2]].max() < 0.1, "E and rho are pinned down by the features"
    assert first.r_surrogate > 0.8


def test_the_diagnostics_check_the_default_posterior(inv) -> None:
    summary = (BUNDLE / "diagnostics" / "summary.md").read_text()
    assert "npe_best64" in summary and "No posterior checked" not in summary
    report = json.loads((BUNDLE / "diagnostics" / "report.json").read_text())
    assert report["posterior_method"] == "npe_best64" and report["heldout"]["rows_used"] == 400
    assert inv.bundle.manifest["diagnostics"]["path"] == "diagnostics"


def test_invert_from_the_command_line_gives_the_library_answer(inv) -> None:
    t = _target(inv, 3)
    items = [a for n, v in t.items() for a in ("--feature", f"{n}={v!r}")]
    res = subprocess.run([sys.executable, "-m", "invphys.cli", "invert", str(BUNDLE), *items, "--json"],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)["results"][0]
    assert out["method"] == "npe_best64"
    got = {n: p["value"] for n, p in out["candidates"][0]["parameters"].items()}
    want = inv.invert(t).parameters
    assert got.keys() == want.keys() and all(np.isclose(got[n], want[n], rtol=1e-9) for n in want)


def test_the_refusal_of_an_unfitted_npe_names_the_fitted_one_or_how_to_add_one(inv) -> None:
    import invphys

    here = str(inv.bundle.unfitted_method_error("npe", "npe"))
    assert "--method npe_best64" in here and "\n" not in here
    quick = invphys.load_inverter(ROOT / "inverters" / "orange_peel_quick").bundle
    there = str(quick.unfitted_method_error("npe", "npe"))
    assert "holds none" in there and all(m in there for m in quick.methods) and "invphys export" in there


@pytest.mark.parametrize("name", ["cheese_cut_quick", "orange_peel_quick"])
def test_invert_with_an_unfitted_npe_type_is_one_line_and_exit_2_without_fitting(inv, name) -> None:
    import time

    import invphys

    bundle = ROOT / "inverters" / name
    other = invphys.load_inverter(bundle)
    items = [a for n, v in zip(other.feature_names, other.bundle.data("test")[1][0].tolist(), strict=True)
             for a in ("--feature", f"{n}={v!r}")]
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "invphys.cli", "invert", str(bundle), "--method", "npe", *items],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert res.returncode == 2 and time.perf_counter() - t0 < 30, (res.returncode, res.stderr)
    line = res.stderr.strip()
    assert line.startswith("error:") and "\n" not in line and "Traceback" not in line
    assert ("--method npe_best64" in line) if name == "cheese_cut_quick" else ("holds none" in line)
