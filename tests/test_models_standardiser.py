"""One standardiser for the project: its rule, and the places that use it (targets, networks, envs)."""

from __future__ import annotations

import numpy as np
import pytest
from models_data import smooth

from invphys.core.standardiser import Standardiser


def test_the_rule_centres_constant_columns_and_ignores_nans() -> None:
    y = np.array([[1.0, 5.0, 0.0], [3.0, 5.0, np.nan], [5.0, 5.0, 2.0]])
    s = Standardiser.fit(y)
    assert s.mean == pytest.approx([3.0, 5.0, 1.0])
    assert s.std == pytest.approx([np.std([1, 3, 5]), 5.0, 1.0])  # constant column: std max(1, |mean|)
    z = s.transform(y)
    assert z[:, 1] == pytest.approx([0, 0, 0]) and s.inverse(z)[0] == pytest.approx(y[0])
    mean, std = s  # unpacks like the (mean, std) pairs it replaced
    assert mean is s.mean and std is s.std
    with pytest.raises(ValueError, match="non-empty"):
        Standardiser.fit(np.zeros((0, 3)))


def test_target_selection_and_objectives_use_it() -> None:
    from invphys.core.objectives import feature_standardiser
    from invphys.core.target_selection import standardise

    y = np.random.default_rng(0).normal(3.0, 2.0, size=(50, 4))
    ref = y[:20]
    assert standardise(y, ref) == pytest.approx(Standardiser.fit(ref).transform(y))
    assert np.array_equal(feature_standardiser(y)[1], Standardiser.fit(y).std)


def test_networks_hold_the_standardiser_of_their_training_features() -> None:
    pytest.importorskip("torch")
    from invphys.plugins.latents.vae import VAELatent
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    theta, y = smooth(64, seed=3)
    y[:, 2] = 7.0  # a constant feature is centred, with std max(1, |mean|) = 7
    tv, yv = theta[:16], y[:16]
    for model in (MLPSurrogate(hidden=(8, 8, 8), max_epochs=2), VAELatent(latent_dim=2, max_epochs=2)):
        model.fit(theta[16:], y[16:], validation=(tv, yv))
        held = model._net.get_standardiser()
        expected = Standardiser.fit(y[16:])
        assert held.mean == pytest.approx(expected.mean, rel=1e-6) and held.std == pytest.approx(expected.std, rel=1e-6)
        assert held.std[2] == pytest.approx(7.0)
