"""The optuna optimiser plugin: Optuna's samplers searching a real small problem through ask/tell, seeded,
within its budget, and writing an Optuna storage only where asked."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from invphys import registry
from invphys.core.errors import InvphysError
from invphys.core.interfaces import Problem, SearchSpace
from invphys.core.spec import parse_spec
from invphys.plugins.optimizers import OptunaOptimizer
from invphys.testing import check_plugin_class

optuna = pytest.importorskip("optuna")

#: the known optimum of the test problem (a shifted quadratic bowl in [0, 1]^4, off-centre)
OPTIMUM = np.array([0.2, 0.7, 0.35, 0.9])


def bowl(seed: int = 0, budget: int = 10_000, initial: np.ndarray | None = None) -> Problem:
    """Maximise -|x - OPTIMUM|^2 over [0, 1]^4; ``problem.info["calls"]`` counts evaluated points."""
    calls: list[int] = []

    def predict(points: np.ndarray) -> np.ndarray:
        calls.append(len(points))
        return np.asarray(points, dtype=np.float64)

    space = SearchSpace("raw", 4, 0.0, 1.0, to_theta=lambda p: p)
    return Problem(space=space, predict=predict, objective=lambda y: -np.sum((y - OPTIMUM) ** 2, axis=1),
                   budget=budget, seed=seed, initial=initial, info={"calls": calls})


def test_registered_by_name_and_meets_the_class_contract() -> None:
    assert registry.get("optimizer", "optuna") is OptunaOptimizer
    check_plugin_class(OptunaOptimizer)
    spec = parse_spec("name: t\nsimulator: {type: \"test_dataset_toy:ToyOscillator\"}\nsurrogate: {type: mlp}\n"
                      "optimizers:\n  tpe: {type: optuna, sampler: tpe, budget: 50}\n"
                      "  cma: {type: optuna, sampler: cmaes, storage: runs/x/optuna.db}\n")
    assert spec.optimizers["cma"]["sampler"] == "cmaes"
    with pytest.raises(InvphysError, match="sampler"):
        parse_spec("name: t\nsimulator: {type: \"test_dataset_toy:ToyOscillator\"}\nsurrogate: {type: mlp}\n"
                   "optimizers:\n  x: {type: optuna, sampler: skopt}\n")


@pytest.mark.parametrize("sampler", ["tpe", "cmaes"])
def test_tpe_and_cmaes_beat_random_search_at_equal_budget(sampler: str) -> None:
    ours, rand = [], []
    for seed in range(3):
        ours.append(OptunaOptimizer(sampler=sampler, budget=160, batch_size=10).optimize(bowl(seed)).score)
        rand.append(OptunaOptimizer(sampler="random", budget=160, batch_size=10).optimize(bowl(seed)).score)
    assert np.median(ours) > np.median(rand)
    assert min(ours) > -0.01  # within 0.1 of the optimum in every seed (random search: ~-0.02)


def test_cmaes_reaches_the_known_optimum_and_spends_exactly_its_budget() -> None:
    problem = bowl(budget=10_000)
    res = OptunaOptimizer(sampler="cmaes", budget=437, batch_size=20).optimize(problem)  # not a multiple
    assert res.evaluations == sum(problem.info["calls"]) == 437
    assert max(problem.info["calls"]) <= 20  # asked and evaluated in batches
    assert np.abs(res.theta - OPTIMUM).max() < 0.02
    assert np.isclose(res.score, -np.sum((res.theta - OPTIMUM) ** 2))
    hist = np.array(res.history)
    assert hist[-1, 0] == 437 and np.all(np.diff(hist[:, 1]) >= 0)
    small = bowl(budget=33)  # the problem's budget caps the optimiser's
    assert OptunaOptimizer(budget=500).optimize(small).evaluations == 33 == sum(small.info["calls"])


def test_seeded_and_deterministic() -> None:
    runs = [OptunaOptimizer(budget=60, batch_size=7).optimize(bowl(seed=5)) for _ in range(2)]
    assert np.array_equal(runs[0].theta, runs[1].theta) and runs[0].history == runs[1].history
    other = OptunaOptimizer(budget=60, batch_size=7).optimize(bowl(seed=6))  # the problem's seed counts
    assert not np.array_equal(runs[0].theta, other.theta)
    fixed = OptunaOptimizer(budget=60, batch_size=7, seed=5).optimize(bowl(seed=6))  # config seed wins
    assert np.array_equal(fixed.theta, runs[0].theta)
    state = np.random.get_state()
    np.random.seed(123)  # the global RNG plays no part
    again = OptunaOptimizer(budget=60, batch_size=7).optimize(bowl(seed=5))
    np.random.set_state(state)
    assert np.array_equal(again.theta, runs[0].theta)


def test_the_initial_point_is_the_first_trial() -> None:
    start = np.array([0.21, 0.69, 0.36, 0.88])
    res = OptunaOptimizer(sampler="tpe", budget=1).optimize(bowl(initial=start))
    assert np.allclose(res.theta, start)


def test_gp_sampler_runs_seeded() -> None:
    pytest.importorskip("torch")
    pytest.importorskip("scipy")
    opts = {"n_startup_trials": 4}
    a = OptunaOptimizer(sampler="gp", budget=6, batch_size=2, sampler_options=opts).optimize(bowl(seed=1))
    b = OptunaOptimizer(sampler="gp", budget=6, batch_size=2, sampler_options=opts).optimize(bowl(seed=1))
    assert a.evaluations == 6 and np.array_equal(a.theta, b.theta)


@pytest.mark.parametrize("filename", ["studies/optuna.db", "optuna.log"])
def test_storage_is_written_where_asked_and_a_rerun_replaces_its_own_study(tmp_path, filename) -> None:
    path = tmp_path / filename
    opt = OptunaOptimizer(budget=12, batch_size=6, storage=str(path), study_name="peel")
    res = opt.optimize(bowl(seed=2))
    assert path.is_file() and res.info["study"].startswith("peel-2-")
    storage = f"sqlite:///{path}" if path.suffix == ".db" else optuna.storages.JournalStorage(
        optuna.storages.journal.JournalFileBackend(str(path)))
    study = optuna.load_study(study_name=res.info["study"], storage=storage)
    assert len(study.trials) == 12 and np.isclose(study.best_value, res.score)
    again = opt.optimize(bowl(seed=2))  # the same problem again: its study is replaced, not appended to
    study = optuna.load_study(study_name=again.info["study"], storage=storage)
    assert len(study.trials) == 12 and np.array_equal(again.theta, res.theta)
    assert len(optuna.get_all_study_names(storage)) == 1


def test_a_study_invphys_did_not_write_is_refused(tmp_path) -> None:
    path = tmp_path / "mine.log"
    opt = OptunaOptimizer(budget=5, storage=str(path), study_name="user")
    name = opt.optimize(bowl(seed=3)).info["study"]
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(path)))
    optuna.delete_study(study_name=name, storage=storage)
    optuna.create_study(study_name=name, storage=storage)  # the user's own study of that name
    with pytest.raises(InvphysError, match="did not write"):
        opt.optimize(bowl(seed=3))
    assert len(optuna.load_study(study_name=name, storage=storage).trials) == 0


def test_nothing_is_written_without_a_storage(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    res = OptunaOptimizer(budget=20).optimize(bowl())
    assert res.info["study"] is None and list(tmp_path.iterdir()) == []


def test_missing_optuna_names_the_extra(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "optuna", None)
    with pytest.raises(InvphysError, match=r"invphys\[optuna\]"):
        OptunaOptimizer(budget=5).optimize(bowl())


def test_bad_sampler_options_are_one_clear_error() -> None:
    with pytest.raises(InvphysError, match="sampler_options"):
        OptunaOptimizer(sampler="tpe", budget=5, sampler_options={"not_an_option": 1}).optimize(bowl())
    with pytest.raises(InvphysError, match="seed"):
        OptunaOptimizer(budget=5, sampler_options={"seed": 1}).optimize(bowl())
