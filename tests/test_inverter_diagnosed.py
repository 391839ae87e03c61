"""Answers of a bundle that holds diagnostics (``invphys diagnose --write``): recalibrated intervals,
calibrated surrogate error bars, and the out-of-distribution warning; a planted unlisted file is refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_inverter_support import paper_bundle

from invphys.core.errors import InvphysError

CALIBRATION = Path(__file__).resolve().parent / "data" / "paper_calibration.json"


@pytest.fixture(scope="module")
def bundles(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from invphys.inverter.manifest import file_hashes, read_manifest, write_manifest

    def rehash(root: Path) -> None:
        manifest = read_manifest(root, verify=False)
        manifest["files"] = file_hashes(root)
        write_manifest(root, manifest)

    plain = paper_bundle(tmp_path_factory.mktemp("plain"))  # without diagnostics (the shipped one has its own)
    shutil.rmtree(plain / "diagnostics", ignore_errors=True)
    rehash(plain)
    diag = tmp_path_factory.mktemp("diag") / "bundle"
    shutil.copytree(plain, diag)
    (diag / "diagnostics").mkdir()
    shutil.copy(CALIBRATION, diag / "diagnostics" / "calibration.json")
    rehash(diag)
    return plain, diag


def _answer(root: Path, y: np.ndarray) -> object:
    from invphys.inverter import load_inverter

    return load_inverter(root).invert(y, method="npe_best64", seed=3)


def test_intervals_are_recalibrated_and_error_bars_scaled(bundles) -> None:
    from invphys.inverter import load_inverter

    plain, diag = bundles
    _, y = load_inverter(plain).bundle.data("test")
    a, b = _answer(plain, y[0]), _answer(diag, y[0])
    assert a.to_dict()["posterior"]["recalibrated"] is False and b.to_dict()["posterior"]["recalibrated"] is True
    np.testing.assert_array_equal(a.theta, b.theta)  # the answer itself is the posterior's own
    ia, ib = a.interval(0.9), b.interval(0.9)  # the intervals move with the stored correction
    assert any(not np.allclose(ia[n], ib[n]) for n in ia)
    scales = json.loads(CALIBRATION.read_text())["surrogate_error_scales"]["scales"]
    np.testing.assert_allclose(b.best.std, a.best.std * np.asarray(scales), rtol=1e-9)


def test_a_target_far_from_the_training_data_is_warned_and_a_typical_one_not(bundles) -> None:
    from invphys.inverter import load_inverter

    plain, diag = bundles
    inv = load_inverter(diag)
    _, y = inv.bundle.data("test")
    std = np.asarray(inv.bundle.manifest["features"]["std"])
    typical, far = _answer(diag, y[1]), _answer(diag, y[1] + 6.0 * std)
    assert not any("unusual target" in w for w in typical.warnings)
    assert any("unusual target" in w for w in far.warnings)
    assert not any("unusual target" in w for w in _answer(plain, y[1] + 6.0 * std).warnings)  # no diagnostics


def test_diagnostics_not_covered_by_the_manifest_are_refused(bundles, tmp_path: Path) -> None:
    """A diagnostics file dropped into a bundle without its checksum (one that silences every warning, say)
    is refused instead of trusted."""
    plain, _ = bundles
    planted = tmp_path / "planted"
    shutil.copytree(plain, planted)
    data = json.loads(CALIBRATION.read_text())
    data["ood"]["threshold"] = 1e9
    (planted / "diagnostics").mkdir()
    (planted / "diagnostics" / "calibration.json").write_text(json.dumps(data))
    with pytest.raises(InvphysError, match=r"calibration\.json"):
        _answer(planted, np.zeros(12))


@pytest.fixture(scope="module")
def failure_bundle(bundles, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The diagnosed bundle plus a failure model fitted on planted failures (answers moved far off the truth)."""
    from invphys.evaluation.diagnose_report import write_failure_into_bundle
    from invphys.evaluation.failure_score import components, fit
    from invphys.inverter.bundle import Bundle

    _, diag = bundles
    root = tmp_path_factory.mktemp("failure") / "bundle"
    shutil.copytree(diag, root)
    (root / "diagnostics" / "report.json").write_text(json.dumps(
        {"bundle_id": json.loads(CALIBRATION.read_text()).get("bundle_id"), "created_utc": "2026-01-01T00:00:00Z",
         "heldout": {"rows_used": 0, "fit_rows": 0, "check_rows": 0},
         "ood": {"chosen": "knn", "threshold": 1.0, "candidates": {}, "check": {"fire_rate": 0.0}},
         "surrogate_error_bars": {}}))
    from invphys.inverter.manifest import file_hashes, read_manifest, write_manifest

    manifest = read_manifest(root, verify=False)
    manifest["files"] = file_hashes(root)
    write_manifest(root, manifest)
    b = Bundle(root)
    theta, y = b.data("test")
    theta, y = np.asarray(theta[:80], dtype=np.float64), np.asarray(y[:80], dtype=np.float64)
    bad = np.arange(80) % 2 == 1
    answers = theta.copy()
    answers[bad] = np.clip(1.0 - answers[bad], 0.0, 1.0)
    write_failure_into_bundle({**fit(components(b, y, answers), bad), "method": "npe_best64"}, root)
    return root


def test_an_answer_likely_to_fail_is_warned_with_its_score_and_a_good_one_not(failure_bundle, bundles) -> None:
    """With a failure model, the warning judges the answer (not only the target): the same target warns
    with a wrong answer and not with its true parameters; without the answer, the target-only warning."""
    from invphys.inverter import load_inverter
    from invphys.inverter.diagnosed import failure_score, ood_warning

    b = load_inverter(failure_bundle).bundle  # verifies: the model is covered by the manifest
    theta, y = b.data("test")
    truth, target, mask = np.asarray(theta[100]), np.asarray(y[100]), np.ones(12, dtype=bool)
    wrong = np.clip(1.0 - truth, 0.0, 1.0)
    assert ood_warning(b, target, mask, truth) == []
    (warn,) = ood_warning(b, target, mask, wrong)
    p = failure_score(b, target, mask, wrong)
    assert p is not None and f"failure score {p:.2f}" in warn and "may not reproduce the target" in warn
    assert failure_score(b, target, mask, truth) < p
    std = np.asarray(b.manifest["features"]["std"])
    assert any("unusual target" in w for w in ood_warning(b, target + 6.0 * std, mask))  # no answer given
    assert failure_score(load_inverter(bundles[1]).bundle, target, mask, truth) is None  # no failure model
    summary = (failure_bundle / "diagnostics" / "summary.md").read_text()
    assert "Failure warning (answer-level" in summary and "Failure warning" in (failure_bundle / "README.md").read_text()
