"""ParameterSpace round trips and bounds checks; R_gt against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from invphys.core.errors import ParameterRangeError
from invphys.core.objectives import WeightedObjective, percentile_scales, recovery_reward
from invphys.core.params import Parameter, ParameterSpace

SPACE = ParameterSpace((
    Parameter("E", 50, 8000, log=True, unit="Pa"),
    Parameter("rho", 0.5, 10),
    Parameter("r_s", 0.001, 0.1, log=True),
))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(0, 1), min_size=3, max_size=3))
def test_unit_round_trip(u):
    u = np.array(u)
    assert np.allclose(SPACE.normalize(SPACE.denormalize(u)), u, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.floats(50, 8000), st.floats(0.5, 10), st.floats(0.001, 0.1))
def test_physical_round_trip(e, rho, r):
    x = np.array([e, rho, r])
    assert np.allclose(SPACE.denormalize(SPACE.normalize(x)), x, rtol=1e-10)


def test_log_scale_matches_table_1():
    # geometric mean of the range sits at 0.5 on a log-scale parameter; arithmetic mean on a linear one
    u = SPACE.normalize([math.sqrt(50 * 8000), (0.5 + 10) / 2, 0.01])
    assert np.allclose(u, [0.5, 0.5, 0.5])
    assert np.allclose(SPACE.denormalize([0, 1, 1]), [50, 10, 0.1])


def test_out_of_range_names_parameter_and_range():
    with pytest.raises(ParameterRangeError, match=r"E = 9000 is outside its range \[50, 8000\] Pa"):
        SPACE.normalize([9000, 1, 0.01])
    with pytest.raises(ParameterRangeError, match=r"normalised rho = 1\.5 is outside"):
        SPACE.denormalize([0.5, 1.5, 0.5])
    with pytest.raises(ParameterRangeError, match="expected 3 parameters"):
        SPACE.normalize([1, 2])


def test_mapping_unknown_and_missing():
    with pytest.raises(ParameterRangeError, match="Did you mean 'rho'"):
        SPACE.from_mapping({"E": 100, "rh": 1, "r_s": 0.01})
    with pytest.raises(ParameterRangeError, match="missing parameter"):
        SPACE.from_mapping({"E": 100})
    x = SPACE.from_mapping({"E": 100}, defaults=SPACE.to_mapping(SPACE.center()))
    assert x[0] == 100


def test_recovery_reward_hand_computed():
    scales = np.array([2.0, 4.0])
    target = np.array([1.0, 1.0])
    assert recovery_reward(target, target, scales) == pytest.approx(1.0)
    # z = (1, 0.5): rms = sqrt((1 + 0.25) / 2) = 0.790569...
    y = np.array([3.0, 3.0])
    assert recovery_reward(y, target, scales) == pytest.approx(math.exp(-3 * math.sqrt(0.625)))
    assert recovery_reward(y, target, scales, kappa=1) == pytest.approx(math.exp(-math.sqrt(0.625)))
    batch = recovery_reward(np.stack([target, y]), target, scales)
    assert batch.shape == (2,) and batch[0] == pytest.approx(1.0)
    assert recovery_reward(np.array([np.nan, 1.0]), target, scales) == 0.0


def test_percentile_scales_and_weighted_objective():
    y = np.stack([np.arange(101.0), np.full(101, 7.0)], axis=1)
    s = percentile_scales(y)
    # a constant feature gets scale max(1, |median|) = 7, not ~0 (it must not dominate R_gt)
    assert s[0] == pytest.approx(90.0) and s[1] == pytest.approx(7.0)
    obj = WeightedObjective.from_names({"a": 1.0, "b": 0.0}, ["a", "b"], y)
    assert obj(np.array([[95.0, 7.0], [5.0, 7.0]])) == pytest.approx([1.0, 0.0])
