"""A pool that ranks its own candidates (``exact``: stored rows by their real R) keeps its order when more than one
candidate is asked for: the first of ``top_k`` candidates is the ``top_k = 1`` answer."""

from __future__ import annotations

import numpy as np
import pytest
from test_inverter_support import paper_inverter


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    return paper_inverter(tmp_path_factory.getbasetemp())


def _pool(inv, targets, top_k, **settings):
    from invphys.inverter.pool import PoolSettings

    inv.pool_settings = PoolSettings().with_(**settings)
    try:
        return inv.invert_many(targets, method="pool", top_k=top_k, seed=0)
    finally:
        inv.pool_settings = PoolSettings()


def test_the_first_of_top_k_candidates_is_the_single_answer_with_exact_rows(inv) -> None:
    theta, y = inv.bundle.data("train")
    rows = [3, 41, 500, 977, 2024]  # training rows as targets: each row itself is the exact answer (R = 1)
    one = _pool(inv, y[rows], 1, exact=True)
    three = _pool(inv, y[rows], 3, exact=True)
    for i, a, b in zip(rows, one, three, strict=True):
        np.testing.assert_array_equal(a.theta, theta[i])
        np.testing.assert_array_equal(b.candidates[0].theta, a.theta)
        assert len(b.candidates) == 3


def test_without_exact_the_first_of_top_k_is_still_the_single_answer(inv) -> None:
    _, y = inv.bundle.data("test")
    one, three = _pool(inv, y[:4], 1), _pool(inv, y[:4], 3)
    for a, b in zip(one, three, strict=True):
        np.testing.assert_array_equal(b.candidates[0].theta, a.theta)
