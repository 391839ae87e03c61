"""Dataset baselines listed as optimisers: fitted by the invert stage, carried fitted in the bundle."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import yaml
from test_inverter_support import toy_run

pytest.importorskip("sbi")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A train + invert run on the shared toy run's data with an npe and a lookup among the optimisers."""
    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    base = tmp_path_factory.getbasetemp()
    store = toy_run(base) / "dataset" / "store"
    spec = {"name": "inverter-baselines", "seed": 3, "simulator": {"type": "test_dataset_toy:ToyOscillator"},
            "dataset": {"path": str(store)},
            "surrogate": {"type": "ensemble", "members": 2, "hidden": [16, 16, 8], "max_epochs": 30, "dropout": 0.0},
            "optimizers": {"npe_best": {"type": "npe", "estimator": "mdn", "hidden_features": 16,
                                        "max_num_epochs": 20, "samples": 16, "answer": "best_surrogate"},
                           "lookup": {"type": "nearest_neighbour"},
                           "cma": {"type": "cma_es", "budget": 100}},
            "targets": {"n": 4}, "stages": ["train", "invert"]}
    out = base / "inverter_baselines_run"
    run_spec(validate_spec(spec), out, progress=False, console=Console(file=io.StringIO()))
    return out


def test_a_fitted_npe_travels_in_the_bundle_and_answers_like_the_invert_stage(run, monkeypatch) -> None:
    from invphys.inverter import load_inverter
    from invphys.plugins.baselines import NPEBaseline

    root = run / "inverter"
    m = yaml.safe_load((root / "manifest.yaml").read_text())
    assert m["methods"]["npe_best"]["path"] == "policies/npe_best" and (root / "policies/npe_best").is_dir()
    assert m["methods"]["npe_best"]["heldout"]["targets"] == 4
    assert (root / m["methods"]["lookup"]["path"]).is_dir()  # the lookup saves its rows' index too
    assert m["default_method"] in ("npe_best", "lookup")  # the best amortised answer on held-out targets

    def no_fit(self, theta, y, scales, progress=False):  # keeps fit's signature: it marks a dataset baseline
        pytest.fail("the bundle's npe was refitted")

    monkeypatch.setattr(NPEBaseline, "fit", no_fit)
    inv = load_inverter(root)
    rows = [r for r in json.loads((run / "invert" / "results.json").read_text()) if r["optimizer"] == "npe_best"]
    targets = np.array(json.loads((run / "invert" / "targets.json").read_text())["features"])
    for r in rows:  # the answer: the best by the surrogate of the target's own first 16 posterior draws
        res = inv.invert(targets[r["target_index"]], method="npe_best", seed=4)
        assert res.evaluations == r["evaluations"] == 17
        draws = inv.posterior(targets[r["target_index"]], n=16, seed=4, method="npe_best").samples[0]
        scores = inv._candidates(draws, ["d"] * 16, res.target, res.mask)
        best = max(range(16), key=lambda j: scores[j].r_surrogate)
        np.testing.assert_array_equal(res.theta, draws[best])


def test_a_lookup_in_the_bundle_answers_with_a_training_row(run) -> None:
    from invphys.inverter import load_inverter

    inv = load_inverter(run / "inverter")
    theta_train, y_train = inv.bundle.data("train")
    res = inv.invert(y_train[5], method="lookup")
    np.testing.assert_allclose(res.theta, theta_train[5], atol=1e-6)


def test_the_three_answer_paths_agree_for_a_bundled_npe(run) -> None:
    """invert (one target), invert_many and the batched invert_array give the same answers."""
    from invphys.inverter import load_inverter

    inv = load_inverter(run / "inverter")
    _, y_test = inv.bundle.data("test")
    many = inv.invert_many(y_test[:6], method="npe_best")
    np.testing.assert_allclose([r.theta for r in many], inv.invert_array(y_test[:6], method="npe_best"), atol=1e-9)
    assert all(r.evaluations == 17 for r in many)  # 16 draws scored + the answer
    top = inv.invert(y_test[0], method="npe_best", top_k=3)
    assert len(top.candidates) == 3 and top.candidates[0].r_surrogate >= top.candidates[-1].r_surrogate


def test_a_partial_target_picks_the_draw_that_best_fits_the_given_features(run, monkeypatch) -> None:
    """Missing features enter a baseline as the training mean, so for a partial target the inverter chooses
    among the baseline's candidates by R over the given features only; a complete target keeps the
    baseline's own answer."""
    from invphys.core.masked_recovery import masked_recovery
    from invphys.inverter import load_inverter

    inv = load_inverter(run / "inverter")
    _, y_test = inv.bundle.data("test")
    given = {inv.feature_names[0]: float(y_test[1][0]), inv.feature_names[3]: float(y_test[1][3])}
    t = inv.targets(given, True)
    draws = np.random.default_rng(0).random((1, 16, 3))
    r = masked_recovery(inv.bundle.surrogate.predict(draws[0]), t.values[0], inv.bundle.scales, t.mask[0],
                        inv.bundle.kappa)
    worst = int(np.argmin(r))  # the baseline "answers" with the draw that fits the given features worst
    from invphys.inverter import answers
    from invphys.inverter import draws as draws_mod

    monkeypatch.setattr(draws_mod, "sample_posterior", lambda plugin, conds, seeds, n: draws_mod.PosteriorDraws(
        np.repeat(draws, len(conds), 0), np.zeros(1), np.zeros(1, int), np.full(1, n), np.ones(1, int)))
    # the method "answers" with the draw that fits the given features worst
    monkeypatch.setattr(answers.PosteriorAnswers, "_choose", lambda self, first, cond, goal: (first[worst], 17))
    res = inv.invert(given, method="npe_best", partial=True)
    assert res.r_surrogate == pytest.approx(float(r.max()), abs=1e-9) and r.max() > r[worst]
    complete = inv.invert(y_test[1], method="npe_best")
    np.testing.assert_allclose(complete.theta, draws[0, worst])
