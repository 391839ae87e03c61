"""local_linear: the lookup refined by a trust-region step of a local linear forward model."""

from __future__ import annotations

import time

import numpy as np
import pytest
from models_data import orange_split

from invphys.core.errors import InvphysError
from invphys.core.objectives import percentile_scales, recovery_reward
from invphys.plugins.baselines import LocalLinear, NearestNeighbour
from invphys.plugins.baselines.local_linear import trust_step
from invphys.registry import default_registry


def _smooth_forward(theta: np.ndarray) -> np.ndarray:
    """A smooth, mildly nonlinear 4-output map of 3 parameters (where a local linear model is valid)."""
    t = np.atleast_2d(theta)
    return np.c_[t[:, 0] + 0.3 * t[:, 1] ** 2, t[:, 1] - 0.2 * t[:, 2], np.sin(2 * t[:, 2]) + 0.1 * t[:, 0],
                 t[:, 0] * t[:, 1] + t[:, 2]]


def test_on_a_smooth_forward_map_it_beats_the_lookup_it_starts_from() -> None:
    rng = np.random.default_rng(0)
    theta = rng.uniform(0, 1, (400, 3))
    y = _smooth_forward(theta)
    truth = rng.uniform(0.1, 0.9, (40, 3))
    targets = _smooth_forward(truth)
    scales = percentile_scales(y)
    nn, ll = NearestNeighbour(), LocalLinear(k=15, ridge=1e-3, trust=2.0)
    nn.fit(theta, y, scales)
    ll.fit(theta, y, scales)
    r_nn = recovery_reward(_smooth_forward(nn.answer(targets).theta), targets, scales)
    ans = ll.answer(targets)
    r_ll = recovery_reward(_smooth_forward(ans.theta), targets, scales)
    assert r_ll.mean() > r_nn.mean() + 0.05 and (r_ll >= r_nn - 0.02).mean() > 0.9
    assert ans.evaluations.sum() == 0 and ans.theta.min() >= 0 and ans.theta.max() <= 1
    # the local model's own prediction of the answer's score is reported
    assert len(ans.info["local_r"]) == 40


def test_trust_step_keeps_its_radius_and_is_least_squares_inside_it() -> None:
    rng = np.random.default_rng(1)
    a, r, scale = rng.normal(size=(6, 4)), rng.normal(size=6), np.array([0.1, 0.2, 0.05, 0.3])
    free = np.linalg.lstsq(a, r, rcond=None)[0]
    np.testing.assert_allclose(trust_step(a, r, scale, 1e6), free, atol=1e-6)
    for radius in (0.1, 1.0, 3.0):
        s = trust_step(a, r, scale, radius)
        assert np.linalg.norm(s / scale) <= radius * (1 + 1e-6)
        assert np.linalg.norm(a @ s - r) < np.linalg.norm(r)  # a descent step
    assert np.all(trust_step(a, r, scale, 0.0) == 0)


def test_zero_trust_answers_the_nearest_row_and_real_data_answers_fast(tmp_path) -> None:
    tt, yt, _te, ye = orange_split()
    scales = percentile_scales(yt)
    nn = NearestNeighbour()
    nn.fit(tt, yt, scales)
    still = LocalLinear(trust=0.0)
    still.fit(tt, yt, scales)
    np.testing.assert_allclose(still.answer(ye).theta, nn.answer(ye).theta)
    ll = LocalLinear(k=12, anchors=3)
    ll.fit(tt, yt, scales)
    t0 = time.perf_counter()
    ans = ll.answer(ye)
    assert (time.perf_counter() - t0) / len(ye) < 0.01  # amortised: well under 10 ms per target
    assert ans.candidates.shape == (len(ye), 3, tt.shape[1]) and np.all(ans.spread > 0)
    # leave-one-out: a training row excluded is not its own neighbour
    idx, _ = ll.neighbours(yt[:5], exclude=np.arange(5))
    assert not np.any(idx == np.arange(5)[:, None])
    again = LocalLinear.load(ll.save(tmp_path / "ll"))
    assert again.config == ll.config
    np.testing.assert_allclose(again.answer(ye).theta, ans.theta)
    with pytest.raises(InvphysError, match="no saved local_linear"):
        LocalLinear.load(tmp_path / "missing")


def test_registered_by_name_and_by_module_path() -> None:
    reg = default_registry()
    assert isinstance(reg.create("optimizer", {"type": "local_linear", "k": 9}), LocalLinear)
    by_path = reg.create("optimizer", {"type": "invphys.plugins.baselines.local_linear:LocalLinear", "trust": 0.5})
    assert isinstance(by_path, LocalLinear) and by_path.config.trust == 0.5
    with pytest.raises(Exception, match="k"):
        reg.create("optimizer", {"type": "local_linear", "k": 1})
