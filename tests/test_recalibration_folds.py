"""The two-fold acceptance rule of posterior recalibration: a parameter is recalibrated only when the
corrections fitted on each half of the held-out rows help on the other half, on average. Planted posteriors whose
two halves are off in opposite directions (what a few hundred rows of noise look like to a map) keep
their own draws; a posterior too narrow on both halves is recalibrated."""

from __future__ import annotations

import json

import numpy as np

from invphys.evaluation import calibration as cal
from invphys.evaluation import recalibration_folds as rf
from invphys.evaluation.diagnose import _recalibration


def planted(n: int = 400, s: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal posteriors in logit space, exact but for: parameter 0 2x too narrow on every row;
    parameter 1 shifted by +0.6 sd on fold A and -0.6 sd on fold B; parameter 2 0.6x as wide as it
    should be on fold A and 1.6x on fold B. Returns (draws (n, s, 3), theta (n, 3), fold_a (n,))."""
    rng = np.random.default_rng(seed)
    fold_a = np.arange(n) % 2 == 0
    mean = rng.normal(0.0, 1.0, (n, 3))
    sd = 0.5
    truth = mean + sd * rng.standard_normal((n, 3))
    width = np.ones((n, 3))
    width[:, 0] = 0.5
    width[:, 2] = np.where(fold_a, 0.6, 1.6)
    shift = np.zeros((n, 3))
    shift[:, 1] = np.where(fold_a, 0.6, -0.6) * sd
    logits = (mean + shift)[:, None, :] + (sd * width)[:, None, :] * rng.standard_normal((n, s, 3))
    return 1 / (1 + np.exp(-logits)), 1 / (1 + np.exp(-truth)), fold_a


def test_only_a_correction_that_helps_out_of_fold_both_ways_is_kept() -> None:
    draws, theta, fold_a = planted()
    result = rf.two_fold(draws, theta, fold_a)
    assert result["keep"] == [True, False, False], result["errors"]
    e = result["errors"]
    # the planted opposite halves: a correction fitted on one half makes the other half worse
    for j in (1, 2):
        assert e["a_to_b"]["after"][j] > e["a_to_b"]["before"][j] and e["b_to_a"]["after"][j] > e["b_to_a"]["before"][j]
    ev = json.loads(json.dumps(rf.evidence(result, ["p0", "p1", "p2"])))
    assert ev["p0"]["recalibrated"] and not ev["p1"]["recalibrated"]
    assert ev["p0"]["a_to_b"]["after"] < ev["p0"]["a_to_b"]["before"] - 0.05


def test_a_large_gain_one_way_outweighs_a_loss_within_noise_the_other_way_and_not_the_reverse() -> None:
    """The rule on the measured errors: the paper bundle's E (800 rows a half) is kept, the cheese
    bundle's E (200 rows a half, worse both ways) and a parameter whose gain is smaller than its loss are not."""
    paper_e = {"a_to_b": {"before": [0.038], "after": [0.020]}, "b_to_a": {"before": [0.019], "after": [0.022]}}
    cheese_e = {"a_to_b": {"before": [0.012], "after": [0.081]}, "b_to_a": {"before": [0.044], "after": [0.064]}}
    lossy = {"a_to_b": {"before": [0.030], "after": [0.025]}, "b_to_a": {"before": [0.020], "after": [0.030]}}
    assert rf.accept(paper_e) == [True] and rf.accept(cheese_e) == [False] and rf.accept(lossy) == [False]


def test_diagnose_stores_a_block_fitted_on_all_rows_that_leaves_rejected_parameters_alone() -> None:
    draws, theta, fold_a = planted(seed=1)
    block, report, fixed = _recalibration(draws, theta, fold_a, ["p0", "p1", "p2"], seed=0)
    assert report["recalibrated"] == ["p0"]
    assert block["maps"][1] is None and block["location_shift"][1] is None and block["location_shift"][2] is None
    assert block == cal.fit_posterior_recalibration(draws, theta, [True, False, False])  # all rows, not one half
    out = cal.apply_posterior_recalibration(draws, json.loads(json.dumps(block)))
    assert np.array_equal(out[:, :, 1:], draws[:, :, 1:]) and not np.allclose(out[:, :, 0], draws[:, :, 0])
    # out of fold, the kept parameter is fixed on the check half and the others are exactly as they were
    assert np.array_equal(fixed[:, :, 1:], draws[~fold_a][:, :, 1:])
    after = report["check_after"]["coverage"]["0.9"]["coverage"]
    assert abs(after[0] - 0.9) < 0.05 and report["recalibration"]["parameters"]["p2"]["recalibrated"] is False
    assert cal.has_recalibration({"posterior": {"recalibration": block}})
    none_kept = cal.fit_posterior_recalibration(draws, theta, [False] * 3)
    assert not cal.has_recalibration({"posterior": {"recalibration": none_kept}})
