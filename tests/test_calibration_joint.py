"""Joint recalibration: per-parameter quantile maps fix each marginal's coverage averaged over rows, but
not a posterior shrunk towards the middle of the box, whose joint coverage (TARP) stays short; the joint
step (a location shift by where each row's posterior sits) fitted on one split restores it on another."""

from __future__ import annotations

import json

import numpy as np
import pytest

from invphys.core.errors import InvphysError
from invphys.evaluation import calibration as cal
from invphys.evaluation.joint_calibration import apply_location_shift

LEVELS = ("0.5", "0.8", "0.9", "0.95")


def shrunk(n: int, s: int, shrink: float, width: float, bias: float, seed: int = 0, d: int = 3
           ) -> tuple[np.ndarray, np.ndarray]:
    """logit(theta) ~ N(0, 1) per parameter, observed with N(0, 0.7^2) noise; the posterior's draws have
    their exact logit mean times ``shrink`` plus ``bias`` and their exact std times ``width``.
    Returns (draws (n, s, d) in the box, theta (n, d))."""
    rng = np.random.default_rng(seed)
    noise = 0.7
    phi = rng.standard_normal((n, d))
    x = phi + noise * rng.standard_normal((n, d))
    var = 1 / (1 + 1 / noise**2)
    logits = (shrink * var * x / noise**2 + bias)[:, None, :] + width * np.sqrt(var) * rng.standard_normal((n, s, d))
    return 1 / (1 + np.exp(-logits)), 1 / (1 + np.exp(-phi))


def joint(draws: np.ndarray, theta: np.ndarray) -> list[float]:
    t = cal.tarp(draws, theta, n_boot=20)
    return [t["levels_refs"][k]["rate"] for k in LEVELS]


def worst_marginal(draws: np.ndarray, theta: np.ndarray) -> float:
    cov = cal.central_coverage(draws, theta, n_boot=20)
    return max(cal.worst_error(cov, j) for j in range(theta.shape[1]))


def off(rates: list[float]) -> float:
    return max(abs(r - float(k)) for r, k in zip(rates, LEVELS, strict=True))


@pytest.mark.parametrize(("width", "bias"), [(0.8, 0.2), (1.3, -0.2)])  # over-confident / under-confident
def test_the_joint_step_restores_tarp_on_another_split_where_per_parameter_maps_do_not(width: float, bias: float
                                                                                       ) -> None:
    draws, theta = shrunk(2400, 300, shrink=0.6, width=width, bias=bias)
    fit = np.arange(len(theta)) % 2 == 0
    maps_only = cal.apply_recalibration(draws[~fit], cal.fit_recalibration(cal.pit_z(draws[fit], theta[fit])))
    block = cal.fit_posterior_recalibration(draws[fit], theta[fit])
    fixed = cal.apply_posterior_recalibration(draws[~fit], block)
    # the per-parameter maps fix every marginal but leave the joint check short by > 0.05 at 50 %
    assert worst_marginal(maps_only, theta[~fit]) < 0.04
    assert joint(maps_only, theta[~fit])[0] < 0.45, joint(maps_only, theta[~fit])
    # maps + the joint step: marginals and TARP within 0.03 of nominal at 50/80/90/95 %
    assert worst_marginal(fixed, theta[~fit]) < 0.04
    assert off(joint(fixed, theta[~fit])) < 0.03, joint(fixed, theta[~fit])
    assert np.all((fixed > 0) & (fixed < 1))
    # each draw keeps its rank within its row for every parameter: the dependence is the posterior's
    for j in range(3):
        assert np.array_equal(np.argsort(fixed[:20, :, j], axis=1), np.argsort(draws[~fit][:20, :, j], axis=1))


def test_a_calibrated_posterior_stays_calibrated() -> None:
    draws, theta = shrunk(2400, 300, shrink=1.0, width=1.0, bias=0.0, seed=3)
    fit = np.arange(len(theta)) % 2 == 0
    fixed = cal.apply_posterior_recalibration(draws[~fit], cal.fit_posterior_recalibration(draws[fit], theta[fit]))
    # 12 coverages of 1,200 rows each: sampling noise alone reaches ~0.04 (one standard error is 0.014)
    assert off(joint(fixed, theta[~fit])) < 0.03 and worst_marginal(fixed, theta[~fit]) < 0.05


def test_the_stored_block_is_plain_json_and_an_answer_is_corrected_alone_as_in_a_batch() -> None:
    draws, theta = shrunk(600, 200, shrink=0.6, width=0.8, bias=0.2, seed=1)
    block = json.loads(json.dumps(cal.fit_posterior_recalibration(draws[:400], theta[:400]), allow_nan=False))
    assert set(block) >= {"maps", "location_shift"}
    diag = {"posterior": {"recalibration": block}}
    batch = cal.recalibrated_samples(draws[400:], diag)
    assert np.array_equal(batch, cal.apply_posterior_recalibration(draws[400:], block))
    assert np.array_equal(batch, cal.recalibrated_samples(draws[400:], diag))  # deterministic
    alone = np.concatenate([cal.recalibrated_samples(draws[i:i + 1], diag) for i in (450, 400, 599)])
    assert np.array_equal(alone, batch[[50, 0, 199]])
    assert cal.has_recalibration(diag) and not cal.has_recalibration(None)
    only_shift = {"posterior": {"recalibration": {"maps": [None] * 3, "location_shift": block["location_shift"]}}}
    assert cal.has_recalibration(only_shift)
    assert not np.array_equal(cal.recalibrated_samples(draws[400:], only_shift), draws[400:])


def test_blocks_without_the_joint_step_apply_their_maps_as_before() -> None:
    draws, theta = shrunk(600, 200, shrink=0.6, width=0.8, bias=0.2, seed=2)
    maps = cal.fit_recalibration(cal.pit_z(draws[:400], theta[:400]))
    old = cal.recalibrated_samples(draws[400:], {"posterior": {"recalibration": {"knots": 21, "maps": maps}}})
    assert np.array_equal(old, cal.apply_recalibration(draws[400:], maps))


@pytest.mark.parametrize("bad", [{"center": 0.5}, {"center": 0.5, "spread": 0.0, "shift": [0, 0], "scale": 1},
                                 {"center": "x", "spread": 1, "shift": [0, 0], "scale": 1},
                                 {"center": 0.5, "spread": 1, "shift": [0], "scale": 1}, "nonsense"])
def test_a_malformed_stored_shift_is_one_clear_error(bad: object) -> None:
    draws, _ = shrunk(4, 50, shrink=1.0, width=1.0, bias=0.0)
    with pytest.raises(InvphysError, match="location shift of parameter 0 is malformed"):
        apply_location_shift(draws, [bad, None, None])
    with pytest.raises(InvphysError, match="3"):
        apply_location_shift(draws, [None, None])


def test_tarp_over_many_reference_points_keeps_the_one_reference_estimate_and_narrows_its_interval() -> None:
    draws, theta = shrunk(800, 200, shrink=1.0, width=1.0, bias=0.0, seed=4)
    one = cal.tarp(draws, theta, n_boot=200, n_refs=1)
    many = cal.tarp(draws, theta, n_boot=200)
    assert one["levels"] == many["levels"]  # the first reference of each row is the one-reference estimate's
    assert np.array_equal(cal.tarp_values(draws, theta, n_refs=5)[:, 0], cal.tarp_values(draws, theta))
    assert many["n_refs"] == cal.TARP_REFS
    assert np.diff(many["levels_refs"]["0.5"]["ci95"])[0] < np.diff(many["levels"]["0.5"]["ci95"])[0]
