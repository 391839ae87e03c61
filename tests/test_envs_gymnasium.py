"""``invphys/Inversion-v0``: registered with Gymnasium, passes its env checker, and means what it says."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from models_data import smooth

gym = pytest.importorskip("gymnasium")


@pytest.fixture(scope="module")
def surrogate(tmp_path_factory):
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    theta, y = smooth(96, d=4 + 5, seed=1)
    model = MLPSurrogate(hidden=(16, 16, 8), max_epochs=8, seed=0)
    model.fit(theta, y)
    directory = model.save(tmp_path_factory.mktemp("sur") / "surrogate")
    return model, directory


def _checked(env) -> list[str]:
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    return [str(w.message) for w in caught]


def test_the_id_is_registered_and_passes_the_env_checker(surrogate) -> None:
    import invphys.envs

    assert "invphys/Inversion-v0" in gym.registry and invphys.envs.register_envs() == ["invphys/Inversion-v0"]
    model, directory = surrogate
    for source in (model, str(directory)):
        env = gym.make("invphys/Inversion-v0", surrogate=source, horizon=4)
        assert _checked(env) == []  # no error and not one warning (bounded spaces, seeding, dtypes)
        assert env.action_space.shape == (9,) and env.observation_space.shape == (9 + 5 + 5 + 2,)


def test_a_step_onto_the_goal_scores_one_and_the_reward_is_the_best_at_t(surrogate) -> None:
    model, _ = surrogate
    action = np.array([0.4, -0.6, 0.2, 0.0, 1.0, -1.0, 0.3, -0.2, 0.5], dtype=np.float32)
    goal = model.predict(0.5 + 0.5 * action[None, :].astype(np.float64))[0]
    env = gym.make("invphys/Inversion-v0", surrogate=model, target=goal, horizon=3)
    obs, _ = env.reset(seed=0)
    assert np.allclose(obs[:9], 0.5) and obs[-1] == 0.0
    obs, reward, terminated, _, info = env.step(action)
    assert info["score"] == pytest.approx(1.0, abs=1e-6) and reward == 0.0 and not terminated
    _, reward, terminated, _, _ = env.step(-action)  # away from the goal: worse score
    _, reward, terminated, truncated, info = env.step(np.zeros(9, dtype=np.float32))
    assert terminated and not truncated and info["score"] < 0.99
    assert reward == pytest.approx(1.0, abs=1e-6)  # the sparse reward is the best of the T states


def test_goals_are_reachable_predictions_and_seeded(surrogate) -> None:
    model, _ = surrogate
    env = gym.make("invphys/Inversion-v0", surrogate=model, goal_samples=64, goal_seed=2)
    task = env.unwrapped.task
    a, _ = env.reset(seed=7)
    b, _ = env.reset(seed=7)
    c, _ = env.reset(seed=8)
    goal_part = slice(9 + 5, 9 + 10)
    assert np.array_equal(a, b) and not np.array_equal(a[goal_part], c[goal_part])
    # the goal in the observation is one of the surrogate's own predictions (standardised)
    goal = task.standardiser.inverse(a[goal_part].astype(np.float64))
    pool = model.predict(np.random.default_rng(2).uniform(0, 1, size=(64, 9)))
    assert np.min(np.abs(pool - goal).max(axis=1)) < 1e-4 * (1 + np.abs(goal).max())


def test_from_an_inverter_bundle_in_its_latent_space(tmp_path_factory) -> None:
    """``bundle=``: a real bundle (the inverter tests' toy run) searched in its flow's latent box."""
    from test_inverter_support import toy_run

    from invphys.inverter import load_inverter

    root = toy_run(tmp_path_factory.getbasetemp()) / "inverter"
    inverter = load_inverter(root)
    bundle = inverter.bundle
    env = gym.make("invphys/Inversion-v0", bundle=str(root), space="flow", horizon=3)
    assert _checked(env) == []  # the checker re-makes the env from its (deep-copied) arguments
    for source in (inverter, bundle):  # a loaded inverter or its bundle work as well
        env = gym.make("invphys/Inversion-v0", bundle=source, space="flow", horizon=3)
        task = env.unwrapped.task
        assert env.action_space.shape == (bundle.latent("flow").latent_dim,)
        assert task.high == pytest.approx(bundle.latent("flow").latent_bound)
    # the reward is the bundle's R_gt: its scales and kappa
    goal = bundle.surrogate.predict(bundle.search_space("flow").to_theta(np.zeros((1, task.dim))))[0]
    env = gym.make("invphys/Inversion-v0", bundle=bundle, space="flow", target=goal, horizon=1)
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step(np.zeros(task.dim, dtype=np.float32))
    # info names the bundle's parameters, in physical units, decoded from the latent point
    theta = bundle.search_space("flow").to_theta(np.zeros((1, task.dim)))[0]
    assert list(info["params"]) == list(bundle.space.names)
    assert list(info["params"].values()) == pytest.approx(bundle.space.denormalize(np.clip(theta, 0, 1)).tolist())
    assert info["units"] == {p.name: p.unit for p in bundle.space.parameters} and info["R"] == pytest.approx(reward)
    from invphys.core.objectives import recovery_reward

    start = bundle.surrogate.predict(bundle.search_space("flow").to_theta(np.zeros((1, task.dim))))[0]
    assert terminated and reward == pytest.approx(float(recovery_reward(start, goal, bundle.scales, bundle.kappa)))


def test_bad_arguments_are_one_clear_error(surrogate) -> None:
    from invphys.core.errors import InvphysError

    model, _ = surrogate
    with pytest.raises(InvphysError, match="exactly one of surrogate"):
        gym.make("invphys/Inversion-v0")
    with pytest.raises(InvphysError, match="needs a bundle"):
        gym.make("invphys/Inversion-v0", surrogate=model, space="vae")
    with pytest.raises(InvphysError, match="no saved surrogate"):
        gym.make("invphys/Inversion-v0", surrogate="/nonexistent/dir")


def test_info_carries_r_and_the_parameters_by_name_in_physical_units(surrogate) -> None:
    """Issue 50: info had only score/best; now R, R_best, theta, params (physical, by name) and units."""
    import invphys.envs  # noqa: F401  (registers the id)
    from invphys.core.params import Parameter, ParameterSpace

    model, _ = surrogate
    space = ParameterSpace(tuple(Parameter(f"p{i}", 1.0, 100.0, log=i % 2 == 0, unit="Pa" if i else "kg")
                                 for i in range(9)))
    env = gym.make("invphys/Inversion-v0", surrogate=model, horizon=2, parameters=space)
    _, info = env.reset(seed=0)
    assert info["theta"] == [0.5] * 9 and info["params"]["p0"] == pytest.approx(10.0)  # log scale: the centre
    assert info["params"]["p1"] == pytest.approx(50.5) and info["units"] == {"p0": "kg", **{f"p{i}": "Pa"
                                                                                          for i in range(1, 9)}}
    action = np.full(9, 1.0, dtype=np.float32)
    _, _, _, _, info = env.step(action)
    assert list(info["params"]) == list(space.names) and info["params"]["p1"] == pytest.approx(100.0)
    assert info["R"] == info["score"] and info["R_best"] == info["best"] and 0.0 <= info["R"] <= 1.0
    bare = gym.make("invphys/Inversion-v0", surrogate=model, horizon=2)  # no space: normalised, named theta_i
    _, info = bare.reset(seed=0)
    assert list(info["params"]) == [f"theta_{i}" for i in range(9)] and info["units"]["theta_0"] == "1"
