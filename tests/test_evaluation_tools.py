"""The protocol's building blocks: bootstrap intervals, paired differences, ask/tell CMA-ES, the
simulator-in-the-loop driver and the uncertainty penalty."""

from __future__ import annotations

import numpy as np
import pytest
from models_data import smooth

from invphys.core.objectives import RecoveryObjective, recovery_reward
from invphys.core.spaces import build_problem, raw_space
from invphys.evaluation.method_summary import actual_score, protocol_summary
from invphys.evaluation.stats import bootstrap_mean_ci, mean_with_ci, paired_difference, spearman


def test_bootstrap_interval_covers_the_mean_and_shrinks_with_more_targets() -> None:
    rng = np.random.default_rng(0)
    small, large = rng.normal(0.6, 0.1, 10), rng.normal(0.6, 0.1, 400)
    m, lo, hi = bootstrap_mean_ci(small)
    assert lo < m < hi and m == pytest.approx(small.mean())
    _, lo2, hi2 = bootstrap_mean_ci(large)
    assert hi2 - lo2 < (hi - lo) / 3  # ~ 1/sqrt(n)
    assert lo2 < 0.6 < hi2
    assert bootstrap_mean_ci([np.nan, 0.5]) == (0.5, 0.5, 0.5)
    assert np.isnan(bootstrap_mean_ci([np.nan])[0])
    m, lo, hi = bootstrap_mean_ci(small)
    assert mean_with_ci(small) == {"mean": m, "ci95": [lo, hi]}  # the JSON form reports store


def test_paired_difference_beats_only_when_the_interval_is_above_zero() -> None:
    rng = np.random.default_rng(1)
    base = rng.uniform(0.3, 0.9, 60)
    better = base + 0.05 + rng.normal(0, 0.02, 60)  # paired: small noise around a clear gain
    same = base + rng.normal(0, 0.05, 60)
    d = paired_difference(better, base)
    assert d["beats"] and d["ci95"][0] > 0 and d["mean_diff"] == pytest.approx(np.mean(better - base))
    assert not paired_difference(same, base)["beats"]
    d_nan = paired_difference([0.5, np.nan, 0.7], [0.4, 0.3, np.nan])
    assert d_nan["n"] == 1
    assert spearman([1, 2, 3, 4], [10, 20, 25, 40]) == pytest.approx(1.0)
    assert np.isnan(spearman([1, 1, 1], [1, 2, 3]))


def test_protocol_summary_scores_failed_runs_as_zero_and_pairs_by_target() -> None:
    rows = []
    for k in range(4):
        rows.append({"optimizer": "nearest_neighbour", "problem": "target", "target_index": k, "validated": True,
                     "r_actual": 0.5, "r_surrogate": 0.6, "gap": 0.1, "failure": None, "evaluations": 0,
                     "wall_time_s": 0.001, "role": "baseline"})
        rows.append({"optimizer": "m", "problem": "target", "target_index": k, "validated": k < 3,
                     "r_actual": float("nan") if k == 2 else 0.8, "r_surrogate": 0.9, "gap": None,
                     "failure": "nan: blew up" if k == 2 else None, "evaluations": 100, "wall_time_s": 0.5,
                     "simulator_runs": 10, "simulator_time_s": 4.0 + k})
    assert actual_score(rows[5]) == 0.0 and np.isnan(actual_score(rows[7]))
    s = protocol_summary(rows, ["farthest_point", "farthest_point", "random", "random"], n_boot=200)
    m = s["m"]
    assert m["n_validated"] == 3 and m["failed"] == 1
    assert m["r_actual_mean"] == pytest.approx((0.8 + 0.8 + 0.0) / 3)
    assert m["vs_nearest_neighbour"]["n"] == 3
    assert m["vs_nearest_neighbour"]["mean_diff"] == pytest.approx((0.3 + 0.3 - 0.5) / 3)
    assert m["simulator_runs"] == 10 and m["evaluations"] == 100
    assert m["simulator_time_s"] == pytest.approx(5.5) and s["nearest_neighbour"]["simulator_time_s"] is None
    assert m["by_set"]["random"]["n_validated"] == 1 and s["nearest_neighbour"]["vs_nearest_neighbour"] is None


def test_ask_tell_cma_es_matches_optimize_and_finds_a_minimum() -> None:
    from invphys.plugins.optimizers.cma_es import CMAES

    target = np.array([0.2, 0.7, 0.4])
    space = raw_space(3)
    cma = CMAES(popsize=8, sigma0=0.3, budget=400)
    search = cma.ask_tell(space, seed=5)
    while not search.done:
        pts = search.ask()
        if len(pts) == 0:
            break
        search.tell(pts, -((pts - target) ** 2).sum(axis=1))
    assert search.told == 400 and np.abs(search.best_point - target).max() < 0.02
    # optimize() is the same loop over a Problem
    problem = build_problem(space, lambda y: -((y - target) ** 2).sum(axis=1), 400, predict=lambda p: p, seed=5)
    res = cma.optimize(problem)
    assert res.evaluations == 400 == problem.info["counter"].count
    np.testing.assert_allclose(res.point, search.best_point)


def test_refine_targets_batches_every_generation_and_never_loses_its_start() -> None:
    from invphys.evaluators.simulator_loop import SimulatorEvaluator, refine_targets

    class Sim:  # a "simulator" with features y = (theta_0 + theta_1, theta_0 * theta_2, theta_1)
        calls: list[int] = []

        def __call__(self, theta):
            from invphys.core.results import RunStats
            from invphys.plugins.validators.simulator import SimulatedFeatures

            self.calls.append(len(theta))
            y = np.c_[theta[:, 0] + theta[:, 1], theta[:, 0] * theta[:, 2], theta[:, 1]]
            return SimulatedFeatures(y, [None] * len(y), [RunStats(device="cpu:test")] * len(y), [None] * len(y))

    sim = Sim()
    ev = SimulatorEvaluator(sim, budget=5 * 25)
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.1, 0.9, (5, 3))
    y_t = np.c_[truth[:, 0] + truth[:, 1], truth[:, 0] * truth[:, 2], truth[:, 1]]
    starts = rng.uniform(0, 1, (5, 3))
    scales = np.ones(3)
    out = refine_targets(y_t, starts, scales, ev, budget=25, popsize=6, sigma0=0.2, seed=0)
    assert sim.calls == [5, 30, 30, 30, 30]  # starts, then 4 generations of 6 for all 5 targets at once
    assert ev.runs == 125 and ev.batches == 5 and ev.device == "cpu:test"
    start_scores = recovery_reward(np.c_[starts[:, 0] + starts[:, 1], starts[:, 0] * starts[:, 2], starts[:, 1]],
                                   y_t, scales)
    for r, s0 in zip(out, start_scores, strict=True):
        assert r.evaluated == 25 and r.score >= s0
    assert np.mean([r.score for r in out]) > np.mean(start_scores)
    with pytest.raises(Exception, match="budget exhausted"):
        ev(starts)


@pytest.fixture(scope="module")
def ensemble():
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

    theta, y = smooth(400, seed=0)
    ens = EnsembleSurrogate(members=3, hidden=(32, 32, 16), max_epochs=40, patience=10, dropout=0.0)
    ens.fit(theta, y)
    return ens


def test_uncertainty_penalty_subtracts_lambda_times_the_normalised_std(ensemble) -> None:
    from invphys.envs.task import InverseTask
    from invphys.evaluators.uncertainty import UncertaintyPenalty, normalised_std, penalised_problem

    theta, y = smooth(20, seed=1)
    scales = np.full(5, 0.5)
    pen = UncertaintyPenalty(ensemble, scales, lam=0.7)
    mean = pen.predict(theta)
    m2, std = ensemble.predict_with_uncertainty(theta)
    np.testing.assert_allclose(mean, m2)
    u = normalised_std(std, scales)
    assert np.all(u > 0)
    obj = RecoveryObjective(y[0], scales)
    np.testing.assert_allclose(pen.objective(obj)(mean), obj(mean) - 0.7 * u)
    assert pen.penalty(mean + 1.0).sum() == 0.0  # features it never predicted: no penalty
    problem = penalised_problem(build_problem(raw_space(9), obj, 50, surrogate=ensemble, target=y[0]),
                                ensemble, scales, 0.7)
    scores = problem.evaluate(theta[:4])
    np.testing.assert_allclose(scores, obj(mean[:4]) - 0.7 * u[:4], rtol=1e-5)  # float32 batches
    assert problem.info["counter"].count == 4
    # GC-PPO's reward: an InverseTask scored with the penalty
    task = InverseTask(low=0.0, high=1.0, dim=9, predict=pen.predict,
                       score=pen.score_fn(lambda f, g: recovery_reward(f, g, scales)),
                       feature_mean=y.mean(0), feature_std=y.std(0))
    feats = task.predict(theta[:3])
    np.testing.assert_allclose(task.score(feats, y[:3]), recovery_reward(feats, y[:3], scales) - 0.7 * u[:3],
                               rtol=1e-5)  # float32 batches


def test_penalised_cma_es_stays_where_the_ensemble_agrees(ensemble) -> None:
    from invphys.evaluators.uncertainty import normalised_std, penalised_problem
    from invphys.plugins.optimizers.cma_es import CMAES

    scales = np.full(5, 0.5)
    _, y = smooth(6, seed=2)
    plain, penal = [], []
    for j, y_t in enumerate(y):
        base = build_problem(raw_space(9), RecoveryObjective(y_t, scales), 300, surrogate=ensemble, target=y_t, seed=j)
        for lam, out in ((0.0, plain), (5.0, penal)):
            res = CMAES(budget=300, popsize=10).optimize(penalised_problem(base, ensemble, scales, lam) if lam else base)
            out.append(float(normalised_std(ensemble.predict_with_uncertainty(res.theta[None])[1], scales)[0]))
    assert np.mean(penal) < np.mean(plain)
