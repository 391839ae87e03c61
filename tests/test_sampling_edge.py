"""The ``edge`` sampler: user-like targets at the edges of the parameter box (evaluation protocol)."""

from __future__ import annotations

import numpy as np

from invphys.core.sampling import EDGE_BAND, sample_unit
from invphys.core.spec import DatasetSection


def test_edge_points_lie_in_the_outer_band_of_every_coordinate_at_both_ends() -> None:
    x = sample_unit(4000, 9, "edge", seed=3)
    assert x.shape == (4000, 9)
    assert np.all((x <= EDGE_BAND) | (x >= 1.0 - EDGE_BAND))
    low = x <= EDGE_BAND
    assert 0.45 < low.mean() < 0.55  # both ends, evenly
    assert abs(np.mean(np.where(low, x, 1.0 - x)) - EDGE_BAND / 2) < 0.005  # uniform inside the band


def test_edge_design_is_seeded_and_prefix_stable() -> None:
    a = sample_unit(50, 4, "edge", seed=7)
    np.testing.assert_array_equal(a, sample_unit(50, 4, "edge", seed=7))
    np.testing.assert_array_equal(a[:20], sample_unit(20, 4, "edge", seed=7))
    assert not np.array_equal(a, sample_unit(50, 4, "edge", seed=8))


def test_spec_accepts_the_edge_sampler() -> None:
    assert DatasetSection(n=10, sampler="edge").sampler == "edge"
