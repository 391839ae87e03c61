"""Validation of orange-peel answers streams through the engine's continuous batching (as dataset generation
does) and gives the features lock-step chunks give."""

from __future__ import annotations

import numpy as np
from invphys_orange_peel.features import OrangePeelFeatures
from invphys_orange_peel.simulator import OrangePeelSimulator

from invphys.plugins.validators.simulator import SimulatorValidator


def test_validation_streams_a_continuous_simulator_with_the_lockstep_features() -> None:
    theta = np.random.default_rng(5).random((3, 9))
    ext = OrangePeelFeatures()
    cont = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=2, frames=12, scheduling="continuous")
    streams: list[int] = []
    inner = cont.simulate_stream

    def spy(params, batch_size=None):
        streams.append(len(params))
        yield from inner(params, batch_size)

    cont.simulate_stream = spy
    got = SimulatorValidator(batch_size=2).simulate_features(theta, cont, ext)
    assert streams == [3]   # one stream over every row
    lock = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=2, frames=12)
    want = SimulatorValidator(batch_size=2).simulate_features(theta, lock, ext)
    assert got.failures == want.failures == [None] * 3
    np.testing.assert_allclose(got.features, want.features, rtol=1e-5, atol=1e-7)
