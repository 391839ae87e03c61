"""Each optimiser improves its objective on a real (briefly trained) surrogate, within its budget."""

from __future__ import annotations

import numpy as np
import pytest
from test_optim_support import _optim_data, random_search_score, recovery_problem

from invphys.core.errors import InvphysError
from invphys.core.objectives import WeightedObjective
from invphys.core.spaces import build_problem, raw_space
from invphys.plugins.optimizers import CMAES, NevergradOptimizer, PPOOptimizer


@pytest.fixture
def optim_data() -> dict:
    """The shared small real problem (trained once per session)."""
    return _optim_data()


def _start_score(problem) -> float:
    return float(problem.objective(problem.predict(np.full((1, problem.space.dim), 0.5)))[0])


def test_cma_es_improves_and_spends_exactly_its_budget(optim_data) -> None:
    target = optim_data["y"][optim_data["test_idx"][3]]
    problem = recovery_problem(optim_data, target, budget=10_000)
    start = _start_score(problem)
    problem.info["counter"].count = 0
    res = CMAES(budget=1010, popsize=20).optimize(problem)  # not a multiple of the popsize
    assert res.evaluations == problem.info["counter"].count == 1010
    assert res.score > start + 0.1 and res.score > 0.8
    assert res.score >= random_search_score(optim_data, target, 1010, seed=0)
    assert np.all((res.theta >= 0) & (res.theta <= 1))
    # the reported score is the objective of the returned point
    assert np.isclose(res.score, problem.objective(optim_data["surrogate"].predict(res.theta[None]))[0])
    hist = np.array(res.history)
    assert np.all(np.diff(hist[:, 1]) >= 0) and hist[-1, 0] == 1010
    # the problem's budget caps the optimiser's
    small = recovery_problem(optim_data, target, budget=37)
    assert CMAES(budget=5000).optimize(small).evaluations == 37 == small.info["counter"].count


def test_cma_es_restarts_to_spend_its_budget_on_a_flat_objective(optim_data) -> None:
    def flat(y):
        return np.zeros(len(y))

    problem = build_problem(raw_space(9), flat, 1000, surrogate=optim_data["surrogate"])
    res = CMAES(budget=1000).optimize(problem)
    assert res.evaluations == problem.info["counter"].count == 1000 and res.info["restarts"] >= 1
    once = build_problem(raw_space(9), flat, 1000, surrogate=optim_data["surrogate"])
    assert CMAES(budget=1000, restarts=False).optimize(once).evaluations < 1000


def test_cma_es_starts_at_the_problems_initial_point(optim_data) -> None:
    target = optim_data["y"][optim_data["test_idx"][4]]
    truth = optim_data["theta"][optim_data["test_idx"][4]]
    problem = recovery_problem(optim_data, target, budget=20, initial=truth)
    res = CMAES(budget=20, sigma0=0.02).optimize(problem)  # one generation around the start
    assert np.allclose(res.info["x0"], truth)
    assert np.abs(res.theta - truth).max() < 0.12
    far = CMAES(budget=20, sigma0=0.02).optimize(recovery_problem(optim_data, target, budget=20))
    assert np.abs(far.theta - 0.5).max() < 0.12  # without an initial point: the box centre


def test_nevergrad_improves_with_batched_asks_and_rejects_unknown_names(optim_data) -> None:
    target = optim_data["y"][optim_data["test_idx"][5]]
    problem = recovery_problem(optim_data, target, budget=10_000)
    start = _start_score(problem)
    problem.info["counter"].count = problem.info["counter"].calls = 0
    res = NevergradOptimizer(optimizer="TwoPointsDE", budget=610, batch_size=20).optimize(problem)
    assert res.evaluations == problem.info["counter"].count == 610
    assert problem.info["counter"].calls == 31  # 30 batches of 20, one of 10
    assert res.score > start + 0.05
    with pytest.raises(InvphysError, match="Did you mean 'NGOpt'"):
        NevergradOptimizer(optimizer="NGOPt", budget=10).optimize(problem)


def test_ppo_improves_a_weighted_objective(optim_data, tmp_path, monkeypatch) -> None:
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # SB3's default logger would write here
    y_tr = optim_data["y"][optim_data["train_idx"]]
    names = [f"f{i}" for i in range(y_tr.shape[1])]
    obj = WeightedObjective.from_names({"f0": 1.0, "f3": -1.0, "f7": 0.5}, names, y_tr, name="firm")
    problem = build_problem(raw_space(9), obj, 100_000, surrogate=optim_data["surrogate"], seed=3,
                            feature_mean=optim_data["mean"], feature_std=optim_data["std"])
    start = _start_score(problem)
    problem.info["counter"].count = 0
    opt = PPOOptimizer(total_timesteps=4096, n_steps=64, n_envs=8, net_arch=[64, 64], seed=0)
    res = opt.optimize(problem)
    assert res.evaluations == problem.info["counter"].count == 1 + 4096 + 8
    assert res.score > start + 0.1
    assert not list(tmp_path.glob("SB3-*")), "SB3 wrote a log folder outside the output directory"
    # the best point is real: re-evaluating it gives its score
    assert np.isclose(res.score, obj(optim_data["surrogate"].predict(res.theta[None]))[0])
    # a budget too small for one update is a clear error
    tiny = build_problem(raw_space(9), obj, 100, surrogate=optim_data["surrogate"],
                         feature_mean=optim_data["mean"], feature_std=optim_data["std"])
    with pytest.raises(InvphysError, match="one update"):
        PPOOptimizer(n_steps=64, n_envs=8).optimize(tiny)


def test_optimizers_are_registered_with_configs() -> None:
    from invphys.registry import Registry

    reg = Registry(autoload=False)
    assert {"cma_es", "nevergrad", "ppo", "gc_ppo", "warm_start"} <= set(reg.names("optimizer"))
    assert "simulator" in reg.names("validator")
    opt = reg.create("optimizer", {"type": "cma_es", "sigma0": 0.2})
    assert opt.config.sigma0 == 0.2 and opt.config.popsize == 20 and opt.config.budget == 5000
    gc = reg.create("optimizer", {"type": "gc_ppo"}).config
    assert (gc.learning_rate, gc.ent_coef, gc.clip_range, gc.gamma, gc.gae_lambda, gc.n_steps, gc.batch_size,
            gc.n_epochs, gc.net_arch, gc.total_timesteps, gc.n_envs, gc.horizon) == \
        (3e-4, 0.01, 0.2, 0.99, 0.95, 256, 64, 10, [256, 256], 500_000, 8, 8)
    ws = reg.create("optimizer", {"type": "warm_start"}).config
    assert (ws.sigma0, ws.popsize, ws.budget, ws.rollouts) == (0.1, 20, 500, 5)
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        reg.create("optimizer", {"type": "cma_es", "sigma0": -1})
