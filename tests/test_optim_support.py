"""Shared data for the optimiser tests: a real MLP surrogate trained briefly on small real data.

The data are ``tests/data/orange_tiny.npz`` (orange-peel runs at the tiny preset) when present, else
a smooth synthetic 9 -> 12 map. Also tests the search spaces and the target selection.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from invphys.core.objectives import RecoveryObjective, percentile_scales
from invphys.core.spaces import build_problem, latent_space, make_predict, raw_space
from invphys.core.target_selection import farthest_point_indices, select_targets

DATA = Path(__file__).parent / "data" / "orange_tiny.npz"


def synthetic(n: int = 600, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth nonlinear map [0, 1]^9 -> R^12 (stands in for the simulator when no real data exists)."""
    rng = np.random.default_rng(seed)
    w = np.random.default_rng(123).normal(size=(9, 12))
    theta = rng.uniform(size=(n, 9))
    y = np.tanh(theta @ w * 0.6 - 0.3 * w.sum(axis=0)) + 0.3 * np.sin(3.0 * theta[:, :1] + theta[:, 1:2])
    return theta, y


@pytest.fixture
def optim_data() -> dict:
    return _optim_data()


@functools.lru_cache(maxsize=1)
def _optim_data() -> dict:
    import torch

    from invphys.plugins.surrogates.mlp import MLPSurrogate

    torch.set_num_threads(1)  # small batches: one thread is fastest, and the machine is shared

    if DATA.is_file():
        with np.load(DATA, allow_pickle=False) as f:
            theta, y = np.asarray(f["theta"], dtype=np.float64), np.asarray(f["y"], dtype=np.float64)
        ok = np.all(np.isfinite(y), axis=1)
        theta, y = theta[ok], y[ok]
    else:
        theta, y = synthetic()
    perm = np.random.default_rng(0).permutation(len(theta))
    n_test = max(10, len(theta) // 5)
    test_idx, train_idx = np.sort(perm[:n_test]), np.sort(perm[n_test:])
    surrogate = MLPSurrogate(hidden=(64, 64, 32), max_epochs=150, patience=25, seed=0, dropout=0.0)
    surrogate.fit(theta[train_idx], y[train_idx])
    y_tr = y[train_idx]
    return {"theta": theta, "y": y, "train_idx": train_idx, "test_idx": test_idx, "surrogate": surrogate,
            "scales": percentile_scales(y_tr), "mean": y_tr.mean(axis=0), "std": y_tr.std(axis=0)}


def recovery_problem(data: dict, target: np.ndarray, budget: int, seed: int = 0, space=None, **kw):
    """A recovery problem for ``target`` on the data's surrogate (decode-then-evaluate)."""
    space = space or raw_space(data["theta"].shape[1])
    return build_problem(space, RecoveryObjective(target, data["scales"]), budget, surrogate=data["surrogate"],
                         target=target, seed=seed, feature_mean=data["mean"], feature_std=data["std"], **kw)


def random_search_score(data: dict, target: np.ndarray, n: int, seed: int) -> float:
    pts = np.random.default_rng(seed).uniform(size=(n, data["theta"].shape[1]))
    return float(RecoveryObjective(target, data["scales"])(data["surrogate"].predict(pts)).max())


# ----------------------------------------------------------------------------------------------
def test_raw_space_is_the_unit_box_and_counts_evaluations(optim_data) -> None:
    sp = raw_space(9)
    assert (sp.low, sp.high, sp.dim) == (0.0, 1.0, 9)
    x = np.array([[-0.5] + [0.3] * 7 + [1.7]])
    assert np.allclose(sp.to_theta(x), [[0.0] + [0.3] * 7 + [1.0]])
    target = optim_data["y"][optim_data["test_idx"][0]]
    p = recovery_problem(optim_data, target, budget=10)
    scores = p.evaluate(np.full((4, 9), 0.5))
    assert scores.shape == (4,) and np.allclose(scores, scores[0])
    assert p.info["counter"].count == 4 and p.info["counter"].calls == 1
    # decode-then-evaluate equals the surrogate on theta
    y = p.predict(np.full((1, 9), 0.25))
    assert np.allclose(y, optim_data["surrogate"].predict(np.full((1, 9), 0.25)))


def test_latent_space_decodes_through_the_model_and_own_head_needs_a_latent() -> None:
    from invphys.core.errors import InvphysError
    from invphys.plugins.latents.realnvp import RealNVPLatent

    theta, y = synthetic(300)
    flow = RealNVPLatent(max_epochs=5, seed=0)
    flow.fit(theta, y)
    sp = latent_space(flow, name="flow")
    assert sp.dim == flow.latent_dim and (sp.low, sp.high) == (-3.0, 3.0)
    z = np.array([[5.0, -5.0, 0.0, 1.0]])[:, : sp.dim]
    th = sp.to_theta(z)
    assert th.shape == (1, 9) and th.min() >= 0.0 and th.max() <= 1.0
    assert np.allclose(th, np.clip(flow.decode(np.clip(z, -3, 3)), 0, 1))
    head = make_predict(sp, None, flow, "own_head")
    assert np.allclose(head(z), flow.predict_features(np.clip(z, -3, 3)))
    with pytest.raises(InvphysError, match="own_head"):
        make_predict(raw_space(9), None, None, "own_head")
    with pytest.raises(InvphysError, match="Did you mean 'shared'"):
        make_predict(raw_space(9), None, None, "shard")


def test_farthest_point_selection_is_spread_deterministic_and_nested() -> None:
    rng = np.random.default_rng(1)
    y = rng.normal(size=(200, 5))
    y[17] = 40.0  # an outlier must be among the first picks
    idx = farthest_point_indices(y, 10)
    assert len(set(idx.tolist())) == 10 and 17 in idx[:2]
    assert np.array_equal(idx, farthest_point_indices(y, 10))
    assert np.array_equal(farthest_point_indices(y, 4), idx[:4])
    # more spread than a random choice: larger minimum pairwise distance
    from scipy.spatial.distance import pdist

    z = (y - y.mean(0)) / y.std(0)
    rand = rng.choice(200, 10, replace=False)
    assert pdist(z[idx]).min() > pdist(z[rand]).min()
    test_idx = np.arange(50, 150)
    rows = select_targets(y, test_idx, 5)
    assert set(rows.tolist()) <= set(test_idx.tolist())
