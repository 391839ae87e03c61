"""corrected_search: local candidates scored by the surrogate corrected with the neighbours' residuals."""

from __future__ import annotations

import numpy as np
import pytest
from models_data import orange_split

from invphys.core.errors import InvphysError
from invphys.core.objectives import percentile_scales, recovery_reward
from invphys.plugins.baselines import CorrectedSearch
from invphys.registry import default_registry


def _forward(theta: np.ndarray) -> np.ndarray:
    t = np.atleast_2d(theta)
    return np.c_[t[:, 0] + 0.3 * t[:, 1] ** 2, t[:, 1] - 0.2 * t[:, 2], np.sin(2 * t[:, 2]), t[:, 0] * t[:, 1]]


def test_the_neighbours_residuals_remove_a_surrogates_bias() -> None:
    rng = np.random.default_rng(0)
    theta = rng.uniform(0, 1, (300, 3))
    y = _forward(theta)
    truth = rng.uniform(0.1, 0.9, (30, 3))
    targets = _forward(truth)
    scales = percentile_scales(y)

    def biased(th):  # a surrogate with a large smooth bias (what a global model gets wrong)
        th = np.atleast_2d(th)
        return _forward(th) + 0.3 * scales * np.c_[th[:, :1], -th[:, 1:2], 0.5 + 0 * th[:, :1], th[:, 2:3]]

    cs = CorrectedSearch(k=20, ridge=1e-3, neighbours=8, budget=48, bandwidth=0.2, seed=3)
    cs.fit(theta, y, scales)
    ans = cs.answer(targets, biased)
    assert (ans.evaluations == 48).all()
    r_true = recovery_reward(_forward(ans.theta), targets, scales)
    # choosing by the uncorrected surrogate among the same candidates does worse
    cands = ans.candidates[:, 8:]
    raw = recovery_reward(biased(cands.reshape(-1, 3)).reshape(30, -1, 4), targets[:, None, :], scales)
    pick = cands[np.arange(30), raw.argmax(1)]
    assert r_true.mean() > recovery_reward(_forward(pick), targets, scales).mean() + 0.03
    # the corrected score of the answer is reported and is the best over the candidates
    assert len(ans.info["corrected_r"]) == 30


def test_it_needs_a_surrogate_and_a_budget_that_leaves_room() -> None:
    tt, yt, _te, ye = orange_split()
    scales = percentile_scales(yt)
    cs = CorrectedSearch(neighbours=8, anchors=4, trusts=[1.0, 2.0], budget=64)
    cs.fit(tt, yt, scales)
    with pytest.raises(InvphysError, match="predict_theta"):
        cs.answer(ye[:2])
    lin = np.linalg.lstsq(np.c_[tt, np.ones(len(tt))], yt, rcond=None)[0]
    ans = cs.answer(ye, lambda th: np.c_[th, np.ones(len(th))] @ lin)
    assert ans.theta.shape == (len(ye), tt.shape[1]) and ans.candidates.shape[1] == 8 + 56
    assert ans.theta.min() >= 0 and ans.theta.max() <= 1
    with pytest.raises(InvphysError, match="budget"):
        CorrectedSearch(neighbours=8, anchors=4, trusts=[1.0, 2.0], budget=16).fit(tt, yt, scales)
    reg = default_registry()
    assert isinstance(reg.create("optimizer", {"type": "invphys.plugins.baselines.corrected_search:CorrectedSearch"}),
                      CorrectedSearch)
