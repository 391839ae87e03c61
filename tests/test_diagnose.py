"""invphys diagnose: coverage, TARP, SBC and recalibration on a posterior whose answer is known; OOD
scores; surrogate error bars; the command end to end on a tiny trained bundle."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_inverter_support import diagnose_app, npe_toy_bundle

from invphys.evaluation import calibration as cal
from invphys.evaluation.surrogate_errors import Z90, error_bar_coverage, fit_error_scales

LEVELS = ("0.5", "0.8", "0.9", "0.95")


def linear_gaussian(n: int, s: int, width: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """theta ~ N(0.5, 0.1^2) per dimension, x = theta + N(0, 0.07^2): the exact posterior is normal.
    Returns (draws (n, s, 3) from the posterior with its std times ``width``, theta (n, 3))."""
    rng = np.random.default_rng(seed)
    sp, sn = 0.1, 0.07
    theta = 0.5 + sp * rng.standard_normal((n, 3))
    x = theta + sn * rng.standard_normal((n, 3))
    var = 1 / (1 / sp**2 + 1 / sn**2)
    mean = var * (0.5 / sp**2 + x / sn**2)
    return mean[:, None, :] + width * np.sqrt(var) * rng.standard_normal((n, s, 3)), theta


def test_the_exact_posterior_covers_at_the_nominal_levels_and_an_overconfident_one_is_flagged() -> None:
    exact, theta = linear_gaussian(1200, 400, 1.0)
    cov = cal.central_coverage(exact, theta, n_boot=200)
    for k in LEVELS:
        assert np.allclose(cov[k]["coverage"], float(k), atol=0.04), (k, cov[k]["coverage"])
        lo, hi = np.array(cov[k]["ci95"]).T
        assert np.all(lo <= np.array(cov[k]["coverage"])) and np.all(np.array(cov[k]["coverage"]) <= hi)
    t = cal.tarp(exact, theta, n_boot=200)
    assert all(abs(t["levels"][k]["rate"] - float(k)) < 0.04 for k in LEVELS)
    assert min(cal.sbc(exact, theta)["ks_pvalue"]) > 1e-3

    narrow, _ = linear_gaussian(1200, 400, 0.6)
    cov = cal.central_coverage(narrow, theta, n_boot=200)
    assert max(cov["0.9"]["coverage"]) < 0.8  # 90 % intervals of a posterior 0.6x too narrow hold ~ 71 %
    assert cal.tarp(narrow, theta, n_boot=200)["atc"] < 0  # sbi's reading: under-dispersed
    assert max(cal.sbc(narrow, theta)["ks_pvalue"]) < 1e-3


def test_a_biased_posterior_reports_the_sign_of_its_bias() -> None:
    draws, theta = linear_gaussian(800, 300, 1.0)
    report = cal.sbc(draws - 0.05, theta)  # posterior shifted low: the truth sits above its median
    assert all(b > 0.1 for b in report["bias"]) and max(report["ks_pvalue"]) < 1e-3


@pytest.mark.parametrize("width", [0.6, 1.6])
def test_recalibration_fitted_on_one_split_fixes_coverage_on_another(width: float) -> None:
    draws, theta = linear_gaussian(2400, 300, width, seed=1)
    fit = np.arange(len(theta)) % 2 == 0
    maps = cal.fit_recalibration(cal.pit_z(draws[fit], theta[fit]))
    before = cal.central_coverage(draws[~fit], theta[~fit], n_boot=50)
    fixed = cal.apply_recalibration(draws[~fit], maps)
    after = cal.central_coverage(fixed, theta[~fit], n_boot=50)
    worst_before = max(cal.worst_error(before, j) for j in range(3))
    worst_after = max(cal.worst_error(after, j) for j in range(3))
    assert worst_before > 0.1 and worst_after < 0.04, (worst_before, worst_after)
    assert np.all((fixed >= 0) & (fixed <= 1))
    # each draw keeps its rank within its row (the posterior's dependence between parameters is kept)
    assert np.array_equal(np.argsort(fixed[:5, :, 0], axis=1), np.argsort(draws[~fit][:5, :, 0], axis=1))
    # the stored form is what an answer applies
    again = cal.recalibrated_samples(draws[~fit], {"posterior": {"recalibration": {"maps": maps}}})
    assert np.array_equal(again, fixed)
    assert cal.recalibrated_samples(draws[~fit], None) is not None
    assert np.array_equal(cal.recalibrated_samples(draws[~fit], None), draws[~fit])


def test_surrogate_error_scales_fitted_on_one_split_hold_ninety_percent_on_another() -> None:
    rng = np.random.default_rng(0)
    n, m = 4000, 4
    std = rng.uniform(0.05, 0.2, size=(n, m))
    y = rng.standard_normal((n, m))
    mean = y + np.array([1.7, 1.0, 0.5, 3.0]) * std * rng.standard_normal((n, m))  # spreads too narrow or wide
    fit = np.arange(n) < n // 2
    before = error_bar_coverage(mean[~fit], std[~fit], y[~fit])
    assert before["per_feature"][3] < 0.5 and before["per_feature"][2] > 0.99
    c = fit_error_scales(mean[fit], std[fit], y[fit])
    after = error_bar_coverage(mean[~fit], std[~fit], y[~fit], c)
    assert all(abs(v - 0.9) < 0.03 for v in after["per_feature"]), after
    assert np.allclose(c, [1.7, 1.0, 0.5, 3.0], rtol=0.1) and Z90 == pytest.approx(1.645, abs=1e-3)


def test_auroc_counts_ranks() -> None:
    from invphys.evaluation.ood import auroc

    assert auroc(np.array([0.1, 0.2, 0.9, 0.8]), np.array([0, 0, 1, 1])) == 1.0
    assert auroc(np.array([0.9, 0.8, 0.1, 0.2]), np.array([0, 0, 1, 1])) == 0.0
    assert np.isnan(auroc(np.ones(3), np.zeros(3)))


def test_cheese_cut_features_given_to_the_orange_bundle_are_refused_by_name() -> None:
    from invphys.evaluation.ood import FeatureMismatch, feature_targets
    from invphys.inverter.bundle import Bundle

    orange = Bundle("inverters/orange_peel_quick", verify=False, allow_legacy=True)
    cheese = Bundle("inverters/cheese_cut_quick", verify=False, allow_legacy=True)
    y = cheese.data("test")[1][:3]
    rows = [dict(zip(cheese.feature_names, r, strict=True)) for r in y.tolist()]
    with pytest.raises(FeatureMismatch, match=r"feature mismatch: .*peak_force.* are not features of bundle"):
        feature_targets(orange, rows)
    with pytest.raises(FeatureMismatch, match="13 features"):
        feature_targets(orange, y)
    assert feature_targets(orange, orange.data("test")[1][:2]).values.shape == (2, 12)


def test_a_bundle_without_a_posterior_gets_its_ood_threshold_and_error_bars(tmp_path) -> None:
    from invphys.evaluation.diagnose import diagnose
    from invphys.evaluation.diagnose_report import write_report
    from invphys.inverter import load_inverter

    d = diagnose(load_inverter("inverters/orange_peel_quick"), draws=10)
    assert d.report["posterior_method"] is None and "no method with a posterior" in d.report["note"]
    assert d.report["heldout"]["rows_used"] == 400 and d.report["heldout"]["training_rows_found"] == 1600
    assert "posterior" not in d.calibration and d.calibration["ood"]["score"] == "knn"
    assert 0.03 < d.report["ood"]["check"]["fire_rate"] < 0.15
    assert abs(d.report["surrogate_error_bars"]["check_after"]["overall"] - 0.9) < 0.03
    names = {p.name for p in write_report(d, tmp_path / "r")}
    assert names == {"report.json", "calibration.json", "summary.md", "rows_used.json"}  # the rows used, by key


def test_the_paper_bundles_held_out_rows_hold_none_of_its_training_rows_whatever_store_they_sit_in() -> None:
    """The shipped paper bundle trained on a join of stores, seed1_v030 among them: held-out rows are
    picked by key, so its rows of that store that are training rows are left out (value-checked)."""
    from scipy.spatial import cKDTree

    from invphys.evaluation.heldout import heldout_rows
    from invphys.inverter.bundle import Bundle

    b = Bundle("inverters/orange_peel_paper", verify=False)
    stores = [f"datasets/orange_peel_paper{s}" for s in ("", "_seed1_v030", "_adaptive", "_adaptive_seed3")]
    held = heldout_rows(b, stores)
    train = b.data("train")[0]
    assert held.info["training_rows_found"] == len(train) == 8256
    assert held.info["stores"]["datasets/orange_peel_paper_seed1_v030"]["training_rows"] == 6656
    assert len(held) == 3344 and not held.info["skipped"]
    assert cKDTree(train).query(held.theta)[0].min() > 1e-6  # by value too: no training row is held out


def test_held_out_rows_are_picked_by_key_not_by_the_store_they_sit_in(bundle, tmp_path) -> None:
    import shutil

    from invphys.evaluation.heldout import heldout_rows
    from invphys.inverter.bundle import Bundle

    b = Bundle(bundle)
    copy = tmp_path / "another_store"  # the training store under another name: its training rows are known by key
    shutil.copytree(b.manifest["dataset"]["path"], copy)
    held = heldout_rows(b, [copy])
    assert held.info["stores"][str(copy)]["training_rows"] == b.manifest["dataset"]["n_train"]
    assert len(held) == b.manifest["dataset"]["n_test"]
    assert np.allclose(np.sort(held.theta, axis=0), np.sort(b.data("test")[0], axis=0))


# -- end to end on a tiny trained bundle ------------------------------------------------------------


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A dataset + train + invert run of the toy oscillator with a small NPE (its bundle's root)."""
    pytest.importorskip("sbi")
    return npe_toy_bundle(tmp_path_factory.mktemp("diagnose") / "run", "diagnose-toy", seed=5, max_epochs=30)


def _cli():
    return diagnose_app()


def test_held_out_rows_are_picked_by_key_and_exclude_every_training_row(bundle) -> None:
    from invphys.core.dataset import DatasetStore, RunIdentity, row_keys
    from invphys.evaluation.heldout import heldout_rows
    from invphys.inverter.bundle import Bundle

    b = Bundle(bundle)
    held = heldout_rows(b)  # from the run's store, not the bundle's copy of its test split
    (store_info,) = held.info["stores"].values()
    assert held.info["training_rows_found"] == held.info["training_rows"] == b.manifest["dataset"]["n_train"]
    assert len(held) == b.manifest["dataset"]["n_test"] and store_info["training_rows"] == held.info["training_rows"]
    ident = RunIdentity(**DatasetStore(b.manifest["dataset"]["path"]).metadata["identity"])
    assert not set(held.keys.tolist()) & set(row_keys(b.data("train")[0], ident))
    assert list(held.keys) == sorted(held.keys)
    assert np.allclose(np.sort(held.theta, axis=0), np.sort(b.data("test")[0], axis=0))


def test_stores_not_sampled_from_the_prior_give_no_held_out_rows(bundle, tmp_path) -> None:
    import shutil

    from invphys.evaluation.heldout import heldout_rows
    from invphys.inverter.bundle import Bundle

    b = Bundle(bundle)
    primary = b.manifest["dataset"]["path"]
    edge = tmp_path / "edge_store"
    shutil.copytree(primary, edge)
    meta = json.loads((edge / "_metadata.json").read_text())
    meta["sessions"] = [{**s, "sampler": "edge"} for s in meta["sessions"]]
    (edge / "_metadata.json").write_text(json.dumps(meta))
    held = heldout_rows(b, [edge])
    assert "not from the prior" in held.info["skipped"][str(edge)]
    assert "test split" in held.info["note"]  # nothing usable: the bundle's own test split, said so


def test_the_ood_score_ranks_a_planted_far_target_above_typical_ones(bundle) -> None:
    from invphys.evaluation.ood import ood_score, ood_threshold
    from invphys.inverter.bundle import Bundle

    b = Bundle(bundle)
    typical = b.data("test")[1]
    far = np.asarray(b.manifest["features"]["mean"]) + 6 * np.asarray(b.manifest["features"]["std"])
    scores = ood_score(b, np.vstack([typical, far]), diagnostics={})
    assert scores[-1] > scores[:-1].max()
    assert ood_threshold(b, diagnostics={}) is None
    given = {b.feature_names[0]: float(far[0])}  # a partial target is scored on what it gives
    assert np.isfinite(ood_score(b, given, diagnostics={})).all()


def test_diagnose_writes_its_report_and_stores_it_in_the_bundle(bundle, tmp_path) -> None:
    from typer.testing import CliRunner

    from invphys.core.errors import InvphysError
    from invphys.inverter.bundle import Bundle

    runner = CliRunner()
    out = tmp_path / "diag"
    res = runner.invoke(_cli(), ["diagnose", str(bundle), "--out", str(out), "--draws", "60", "--json", "--write"])
    assert res.exit_code == 0, res.output
    report = json.loads(res.stdout, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))  # strict JSON
    names = list(Bundle(bundle).space.names)
    assert report["heldout"]["rows_used"] == Bundle(bundle).manifest["dataset"]["n_test"]
    assert set(report["check_before"]["coverage"]) == set(LEVELS)
    assert len(report["check_before"]["sbc"]["ks_pvalue"]) == len(names)
    assert 0.0 <= report["check_after"]["tarp"]["levels"]["0.9"]["rate"] <= 1.0
    assert 0.0 <= report["outside_box"]["clipped_share"] <= 1.0
    assert set(report["ood"]["candidates"]) >= {"knn", "misfit", "ensemble_std", "outside_fraction"}
    failing = report["ood"]["failure"]["failing_check"]   # the failing check rows each AUROC rests on
    assert set(failing) == {"parameter_error", "r_surr"} and all(isinstance(n, int) and n >= 0 for n in failing.values())
    assert f"({failing['r_surr']} failing rows" in (out / "summary.md").read_text() or \
        f"on only {failing['r_surr']} failing rows" in (out / "summary.md").read_text()
    for f in ("report.json", "calibration.json", "summary.md", "rank_histograms.png", "coverage.png"):
        assert (out / f).is_file(), f
    calib = json.loads((out / "calibration.json").read_text())
    assert len(calib["posterior"]["recalibration"]["maps"]) == len(names)
    assert np.isfinite(calib["ood"]["threshold"]) and len(calib["surrogate_error_scales"]["scales"]) == len(Bundle(bundle).feature_names)
    b = Bundle(bundle)  # re-hashed: still verifies
    assert "diagnostics/calibration.json" in b.manifest["files"] and b.manifest["diagnostics"]["path"] == "diagnostics"
    assert "## Diagnostics (invphys diagnose)" in (bundle / "README.md").read_text()
    again = runner.invoke(_cli(), ["diagnose", str(bundle), "--out", str(out), "--draws", "60"])
    assert again.exit_code == 2 and "not empty" in again.output
    assert runner.invoke(_cli(), ["diagnose", str(bundle)]).exit_code == 2
    from invphys.evaluation.ood import load_diagnostics

    assert load_diagnostics(Bundle(bundle))["ood"]["threshold"] == calib["ood"]["threshold"]
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "diagnostics").mkdir()
    (broken / "diagnostics" / "calibration.json").write_text("{not json")
    with pytest.raises(InvphysError, match="not a JSON object"):
        load_diagnostics(type("B", (), {"root": broken})())
    rewrite = runner.invoke(_cli(), ["diagnose", str(bundle), "--write", "--draws", "20"])
    assert rewrite.exit_code == 0, rewrite.output
    assert (bundle / "README.md").read_text().count("## Diagnostics (invphys diagnose)") == 1
    assert sorted(p.name for p in bundle.parent.iterdir() if p.name.startswith(".")) == []  # no copy left over
    Bundle(bundle)


def test_diagnose_fits_the_failure_warning_from_validated_answers_and_keeps_it(bundle, tmp_path) -> None:
    from invphys.core.errors import InvphysError
    from invphys.evaluation.diagnose import diagnose
    from invphys.evaluation.diagnose_report import write_into_bundle
    from invphys.evaluation.heldout import heldout_rows
    from invphys.inverter import load_inverter

    inv = load_inverter(bundle)
    held = heldout_rows(inv.bundle)
    bad = np.arange(len(held)) % 3 == 0
    answers = np.where(bad[:, None], 1.0 - held.theta, held.theta)
    r = np.where(bad, 0.3, 0.95)
    path = tmp_path / "validated.json"
    path.write_text(json.dumps({"validated": True, "sets": {"heldout": {
        "keys": held.keys.tolist(), "y": held.y.tolist(), "truth_theta": held.theta.tolist(),
        "methods": {inv.default_method: {"theta": answers.tolist(), "r_actual": r.tolist()}}}}}))
    with pytest.raises(InvphysError, match="no set named nope"):
        diagnose(inv, draws=20, failures=f"{path}:nope")
    d = diagnose(inv, draws=20, failures=path)
    f = d.calibration["failure"]
    assert f == d.report["failure"] and f["rows"]["used"] == len(held) and f["rows"]["training_rows"] == 0
    assert f["threshold_rule"]["rule"] == "alarms" and f["scores"] == ["knn", "misfit", "local_error"]
    assert f["calibration"]["alarm_rate"] <= f["threshold_rule"]["allowed"] and f["calibration"]["recall"] > 0
    write_into_bundle(d, bundle)
    assert "Failure warning (answer-level" in (bundle / "diagnostics" / "summary.md").read_text()
    kept = diagnose(load_inverter(bundle), draws=20).calibration["failure"]  # no --failures: the stored one stays
    assert kept["threshold"] == f["threshold"] and "previous diagnostics" in kept["kept"]
    from invphys.evaluation.diagnose import _failure

    (bundle / "diagnostics" / "calibration.json").write_text("{not json")  # unreadable: nothing to keep, no stop
    from invphys.inverter.bundle import Bundle

    assert _failure(type("Inv", (), {"bundle": Bundle(bundle, verify=False)})(), None) is None


def test_an_auroc_on_few_failing_rows_says_so() -> None:
    from invphys.evaluation.diagnose_report import FEW_FAILING, _auc

    assert _auc(0.99, 3) == "0.99 (on only 3 failing rows: too few to rank the score)"
    assert _auc(0.81, FEW_FAILING) == f"0.81 ({FEW_FAILING} failing rows)"
    assert _auc(0.5, None) == "0.50"   # a report written before the counts: the number alone
