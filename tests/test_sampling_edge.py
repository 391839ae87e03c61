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


def test_faces_points_put_each_coordinate_in_the_band_half_the_time_and_stay_in_the_box() -> None:
    x = sample_unit(40_000, 9, "faces", seed=5)
    assert x.shape == (40_000, 9) and x.min() >= 0.0 and x.max() <= 1.0
    in_band = (x <= EDGE_BAND) | (x >= 1.0 - EDGE_BAND)
    assert abs(in_band.mean() - (0.5 + 0.5 * 2 * EDGE_BAND)) < 0.01  # half in the band, plus uniform's share
    assert abs((x <= EDGE_BAND).mean() - (x >= 1.0 - EDGE_BAND).mean()) < 0.01  # both ends
    assert abs(in_band.all(axis=1).mean() - 0.6 ** 9) < 0.002  # corners: all 9 in the band, ~1 %
    np.testing.assert_array_equal(x[:100], sample_unit(100, 9, "faces", seed=5))  # prefix-stable
    assert DatasetSection(n=10, sampler="faces").sampler == "faces"


def test_unit_density_matches_each_design_and_is_one_for_the_prior_samplers() -> None:
    from invphys.core.sampling import unit_density

    pts = np.array([[0.05, 0.95], [0.05, 0.5], [0.5, 0.5]])
    np.testing.assert_allclose(unit_density(pts, "uniform"), 1.0)
    np.testing.assert_allclose(unit_density(pts, "edge"), [25.0, 0.0, 0.0])  # (0.5 / 0.1) per coordinate
    np.testing.assert_allclose(unit_density(pts, "faces"), [3.0 * 3.0, 3.0 * 0.5, 0.25])
    # a histogram of the design agrees with its density on one coordinate's cells
    x = sample_unit(200_000, 1, "faces", seed=1)[:, 0]
    hist, edges = np.histogram(x, bins=20, range=(0, 1), density=True)
    centres = (edges[:-1] + edges[1:]) / 2
    np.testing.assert_allclose(hist, unit_density(centres[:, None], "faces"), rtol=0.05)
