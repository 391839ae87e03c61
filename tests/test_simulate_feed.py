"""The default ``Simulator.simulate_feed``: an open stream over a simulator without one of its own."""

from __future__ import annotations

import numpy as np
from test_dataset_toy import ToyOscillator

from invphys.core.errors import SimulationFailed


class FailingToy(ToyOscillator):
    """Raises :class:`SimulationFailed` for any batch holding a row with damping c above 0.5."""

    def simulate(self, params, on_result=None):
        if (np.atleast_2d(params)[:, 1] > 0.5).any():
            raise SimulationFailed("blow-up: c too large")
        return super().simulate(params, on_result)


def test_default_feed_numbers_rows_in_feed_order_and_isolates_failures() -> None:
    sim = FailingToy()
    rows = [np.array([[10.0, 0.1, 1.0], [20.0, 0.9, 1.0], [30.0, 0.2, 1.0]]), np.array([[40.0, 0.3, 1.5]])]
    asked = []

    def feeder(free):
        asked.append(free)
        return rows.pop(0) if rows else None

    got = dict(sim.simulate_feed(feeder, batch_size=4))
    assert sorted(got) == [0, 1, 2, 3] and asked == [4, 4, 4]
    assert not got[1].ok and got[1].failure == "blow-up: c too large"
    plain = ToyOscillator().simulate(np.array([[10.0, 0.1, 1.0], [30.0, 0.2, 1.0], [40.0, 0.3, 1.5]]))
    for i, ref in zip((0, 2, 3), plain, strict=True):
        assert got[i].ok
        np.testing.assert_array_equal(got[i].trajectory.positions, ref.trajectory.positions)
    assert list(sim.simulate_feed(lambda free: np.empty((0, 3)))) == []
