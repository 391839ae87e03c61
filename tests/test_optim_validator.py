"""The simulator validator: its numbers equal a direct simulator run's; failures are recorded."""

from __future__ import annotations

import numpy as np
import pytest

from invphys.core.errors import InvphysError
from invphys.core.objectives import recovery_reward
from invphys.plugins.validators import SimulatorValidator


def test_validator_matches_a_direct_run() -> None:
    from test_dataset_toy import SIM

    from invphys.registry import Registry

    reg = Registry()
    block = {"type": SIM, "n_frames": 36}
    sim = reg.create("simulator", block)
    ext = reg.create("feature_extractor", sim.default_feature_extractor())
    rng = np.random.default_rng(0)
    theta = rng.uniform(0.2, 0.8, size=(2, 3))
    # validation on a shorter run than the spec's simulator: overrides are applied
    val = SimulatorValidator(overrides={"n_frames": 24}, batch_size=2)
    direct_sim = reg.create("simulator", {**block, "n_frames": 24})
    direct = direct_sim.simulate(direct_sim.parameter_space().denormalize(theta))
    assert all(r.ok for r in direct)
    actual = np.stack([ext.extract(r.trajectory) for r in direct])
    longer = sim.simulate(sim.parameter_space().denormalize(theta))
    assert not np.allclose(np.stack([ext.extract(r.trajectory) for r in longer]), actual)  # the override counts
    targets = actual[::-1] + 0.01  # target of row 0 is row 1's behaviour, and vice versa
    predicted = actual + 0.005
    scales = np.abs(actual).mean(axis=0) + 1e-3
    recs = val.validate(theta, targets, predicted, sim, ext, scales)
    assert len(recs) == 2
    for i, rec in enumerate(recs):
        assert rec.failure is None
        np.testing.assert_allclose(rec.actual, actual[i], rtol=1e-6, atol=1e-9)
        assert rec.r_actual == pytest.approx(float(recovery_reward(actual[i], targets[i], scales)), rel=1e-6)
        assert rec.r_surrogate == pytest.approx(float(recovery_reward(predicted[i], targets[i], scales)))
        assert rec.gap == pytest.approx(rec.r_surrogate - rec.r_actual)
        assert rec.stats is not None and rec.stats.preset == "tiny"


def test_validator_records_failed_runs_and_checks_overrides() -> None:
    from test_dataset_toy import ToyFeatures, ToyOscillator

    sim, ext = ToyOscillator(), ToyFeatures()
    # k at the top of its range with light mass: omega * dt > 2, the integrator blows up
    theta = np.array([[0.2, 0.5, 0.5], [1.0, 0.0, 0.0], [0.6, 0.3, 0.9]])
    direct = sim.simulate(sim.parameter_space().denormalize(theta))
    assert [r.ok for r in direct] == [True, False, True]
    feats = np.stack([ext.extract(r.trajectory) for r in direct if r.ok])
    targets = np.stack([feats[1], feats[0], feats[1]])
    scales = np.ones(feats.shape[1])
    recs = SimulatorValidator(batch_size=2).validate(theta, targets, targets, sim, ext, scales)
    assert recs[1].failure and "blow-up" in recs[1].failure and np.isnan(recs[1].r_actual)
    assert recs[1].actual is None and recs[1].r_surrogate == pytest.approx(1.0)
    np.testing.assert_allclose(recs[0].actual, feats[0])
    np.testing.assert_allclose(recs[2].actual, feats[1])
    assert recs[2].r_actual == pytest.approx(1.0) and recs[2].gap == pytest.approx(0.0)
    assert recs[0].r_actual == pytest.approx(float(recovery_reward(feats[0], feats[1], scales)))
    with pytest.raises(InvphysError, match="overrides"):
        SimulatorValidator(overrides={"n_frames": 1}).validate(theta, targets, targets, sim, ext, scales)
    with pytest.raises(InvphysError, match="differ in number"):
        SimulatorValidator().validate(theta, targets[:2], targets, sim, ext, scales)
