"""The dataset baselines: nearest-neighbour lookup and sbi's NPE, on real data and a synthetic problem
with one parameter the features cannot see."""

from __future__ import annotations

import json

import numpy as np
import pytest
from models_data import orange_split

from invphys.core.errors import InvphysError
from invphys.core.objectives import RecoveryObjective, percentile_scales
from invphys.core.spaces import build_problem, raw_space
from invphys.plugins.baselines import NearestNeighbour, NPEBaseline


def _linear(theta_train, y_train):
    """A least-squares linear surrogate theta -> y (a real, cheap model for best-of-k choices)."""
    a = np.c_[theta_train, np.ones(len(theta_train))]
    w, *_ = np.linalg.lstsq(a, y_train, rcond=None)
    return lambda th: np.c_[np.atleast_2d(th), np.ones(len(np.atleast_2d(th)))] @ w


def test_nearest_neighbour_returns_the_closest_training_rows_parameters() -> None:
    tt, yt, _te, ye = orange_split()
    scales = percentile_scales(yt)
    nn = NearestNeighbour()
    nn.fit(tt, yt, scales)
    # a training row is its own nearest neighbour
    np.testing.assert_allclose(nn.answer(yt[:20]).theta, tt[:20])
    ans = nn.answer(ye)
    z = (ye[:, None, :] - yt[None, :, :]) / scales
    brute = np.argmin(np.sqrt((z ** 2).sum(-1)), axis=1)
    np.testing.assert_allclose(ans.theta, tt[brute])
    assert ans.evaluations.sum() == 0 and np.isnan(ans.spread).all()  # one candidate: no spread


def test_nearest_neighbour_saves_and_loads(tmp_path) -> None:
    tt, yt, _te, ye = orange_split()
    nn = NearestNeighbour(k=3, metric="standardised", select="mean")
    nn.fit(tt, yt, percentile_scales(yt))
    again = NearestNeighbour.load(nn.save(tmp_path / "nn"))
    assert again.config == nn.config and again.fitted
    np.testing.assert_allclose(again.answer(ye).theta, nn.answer(ye).theta)
    with pytest.raises(InvphysError, match="no saved nearest_neighbour"):
        NearestNeighbour.load(tmp_path / "missing")


def test_nearest_neighbour_k_metrics_and_selection() -> None:
    tt, yt, _te, ye = orange_split()
    scales = percentile_scales(yt)
    std = NearestNeighbour(k=5, metric="standardised", select="mean")
    std.fit(tt, yt, scales)
    idx, dist = std.neighbours(ye[:7])
    assert idx.shape == (7, 5) and np.all(np.diff(dist, axis=1) >= -1e-12)  # nearest first
    np.testing.assert_allclose(std.answer(ye[:7]).theta, tt[idx].mean(axis=1))
    predict = _linear(tt, yt)
    by_surr = NearestNeighbour(k=8, select="surrogate")
    by_surr.fit(tt, yt, scales)
    ans = by_surr.answer(ye[:7], predict)
    assert (ans.evaluations == 8).all() and ans.spread.shape == (7, 9) and np.all(ans.spread > 0)
    obj = [RecoveryObjective(y, scales) for y in ye[:7]]
    cands = ans.candidates
    chosen = [float(obj[i](predict(ans.theta[i][None]))[0]) for i in range(7)]
    best = [max(float(obj[i](predict(c[None]))[0]) for c in cands[i]) for i in range(7)]
    assert chosen == pytest.approx(best)
    with pytest.raises(InvphysError, match="surrogate"):
        by_surr.answer(ye[:2])


def test_a_baseline_is_an_optimiser_over_a_problem_and_says_when_it_was_not_fitted() -> None:
    tt, yt, _te, ye = orange_split()
    scales = percentile_scales(yt)
    predict = _linear(tt, yt)
    nn = NearestNeighbour(k=4, select="surrogate")
    with pytest.raises(InvphysError, match=r"evaluation\.baselines"):
        nn.prepare(raw_space(9), predict, yt, scales)
    nn.fit(tt, yt, scales)
    problem = build_problem(raw_space(9), RecoveryObjective(ye[0], scales), budget=10, predict=predict,
                            target=ye[0], info={"theta_predict": predict})
    res = nn.optimize(problem)
    assert res.evaluations == 4 + 1 and problem.info["counter"].count == 1  # 4 choices, 1 score
    assert res.score == pytest.approx(float(RecoveryObjective(ye[0], scales)(predict(res.theta[None]))[0]))
    with pytest.raises(InvphysError, match="target"):
        nn.optimize(build_problem(raw_space(9), RecoveryObjective(ye[0], scales), 5, predict=predict))


def test_a_baseline_as_a_penalised_optimiser_chooses_by_the_penalised_score() -> None:
    from invphys.evaluators.uncertainty import penalised_problem

    tt, yt, _te, ye = orange_split()
    scales = percentile_scales(yt)
    predict = _linear(tt, yt)

    class Doubtful:  # doubts every parameter vector but the lookup's first candidate's
        first: np.ndarray | None = None

        def predict_with_uncertainty(self, th):
            th = np.atleast_2d(th)
            if self.first is None:
                self.first = th[0].copy()
            std = np.where(np.all(np.isclose(th, self.first), axis=1)[:, None], 0.0, 10.0)
            return predict(th), np.broadcast_to(std, (len(th), yt.shape[1]))

    nn = NearestNeighbour(k=4, select="surrogate")
    nn.fit(tt, yt, scales)
    base = build_problem(raw_space(9), RecoveryObjective(ye[1], scales), budget=10, predict=predict, target=ye[1],
                         info={"theta_predict": predict})
    doubtful = Doubtful()
    res = nn.optimize(penalised_problem(base, doubtful, scales, lam=5.0))
    np.testing.assert_allclose(res.theta, doubtful.first)  # the only candidate without a penalty


def _hidden_parameter_problem(n: int = 600, seed: int = 0):
    """theta in [0,1]^2; the features see theta_0 only (theta_1 cannot be pinned down)."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0, 1, (n, 2))
    y = np.c_[theta[:, 0], theta[:, 0] ** 2] + rng.normal(0, 0.01, (n, 2))
    return theta, y


@pytest.fixture(scope="module")
def npe_fitted():
    theta, y = _hidden_parameter_problem()
    npe = NPEBaseline(estimator="mdn", hidden_features=24, max_num_epochs=60, stop_after_epochs=10,
                      training_batch_size=32, learning_rate=2e-3, samples=64, seed=1)
    npe.fit(theta, y, percentile_scales(y))
    return npe


def test_npe_pins_down_what_the_features_see_and_flags_what_they_do_not(npe_fitted) -> None:
    theta, y = _hidden_parameter_problem(40, seed=5)
    ans = npe_fitted.answer(y)
    assert ans.candidates.shape == (40, 64, 2) and ans.theta.shape == (40, 2)
    spread = ans.spread.mean(axis=0)
    assert spread[0] < 0.5 < spread[1]  # theta_0 pinned down, theta_1 about as wide as the prior
    assert np.abs(ans.theta[:, 0] - theta[:, 0]).mean() < 0.1
    mean = NPEBaseline(npe_fitted.config.model_copy(update={"answer": "mean"})).adopt(npe_fitted)
    assert mean.fitted and mean.metrics["shared_fit"] and mean.fit_key() == npe_fitted.fit_key()
    np.testing.assert_allclose(mean.answer(y).theta, ans.candidates.mean(axis=1), atol=1e-6)


def test_npe_best_of_k_by_surrogate_and_save_load(npe_fitted, tmp_path) -> None:
    theta, y = _hidden_parameter_problem(10, seed=6)
    surr = NPEBaseline(npe_fitted.config.model_copy(update={"answer": "best_surrogate"})).adopt(npe_fitted)
    predict = lambda th: np.c_[th[:, 0], th[:, 0] ** 2]  # noqa: E731 (the true, noise-free map)
    ans = surr.answer(y, predict)
    assert (ans.evaluations == 64).all()
    err_best = np.abs(ans.theta[:, 0] - theta[:, 0]).mean()
    assert err_best <= np.abs(ans.candidates[:, :, 0] - theta[:, None, 0]).mean() + 1e-12
    npe_fitted.save(tmp_path / "npe")
    again = NPEBaseline.load(tmp_path / "npe")
    np.testing.assert_allclose(again.answer(y).theta, npe_fitted.answer(y).theta)
    with pytest.raises(InvphysError, match="no saved npe"):
        NPEBaseline.load(tmp_path / "missing")


class _StdGrowsWithHiddenParameter:
    """A surrogate that predicts the true map but doubts itself in proportion to theta_1 (which the features
    hardly see: a 1e-6 trace keeps predictions of different draws apart, as the penalty looks stds up by them)."""

    def predict(self, th):
        th = np.atleast_2d(th)
        return np.c_[th[:, 0] + 1e-6 * th[:, 1], th[:, 0] ** 2]

    def predict_with_uncertainty(self, th):
        th = np.atleast_2d(th)
        return self.predict(th), np.repeat(th[:, 1:2], 2, axis=1)


def test_npe_penalised_pick_prefers_draws_the_ensemble_agrees_on(npe_fitted) -> None:
    from invphys.evaluation.answers import baseline_rows
    from invphys.evaluators.uncertainty import UncertaintyPenalty

    theta, y = _hidden_parameter_problem(10, seed=7)
    surrogate, scales = _StdGrowsWithHiddenParameter(), npe_fitted._scales
    plain = NPEBaseline(npe_fitted.config.model_copy(update={"answer": "best_surrogate"})).adopt(npe_fitted)
    cfg = npe_fitted.config.model_copy(update={"answer": "best_surrogate", "uncertainty_penalty": 100.0})
    pen_npe = NPEBaseline(cfg).adopt(npe_fitted)
    assert pen_npe.fit_key() == plain.fit_key()  # the penalty is an answer option: one fit serves both
    pen = UncertaintyPenalty(surrogate, scales, 100.0)
    a, b = plain.answer(y, surrogate.predict), pen_npe.answer(y, pen.predict, pen.penalty)
    np.testing.assert_allclose(a.candidates, b.candidates)
    # with a large lambda the pick is the draw with the smallest theta_1 (the least doubted one)
    np.testing.assert_allclose(b.theta[:, 1], b.candidates[:, :, 1].min(axis=1))
    assert b.theta[:, 1].mean() < a.theta[:, 1].mean()
    # through the evaluation's baseline rows: the ensemble's std is used, and a surrogate without it is refused
    targets = {"features": y.tolist(), "rows": list(range(10)), "theta": theta.tolist(),
               "selection": ["random"] * 10, "param_names": ["a", "b"]}
    to_params = lambda th: list(map(float, th))  # noqa: E731
    fitted = NPEBaseline(cfg).adopt(npe_fitted)
    fitted.fit = lambda *a, **k: fitted.metrics  # keep the module's fit (baseline_rows fits on the rows given)
    rows, metrics = baseline_rows({"npe_pen": fitted}, theta, y, scales, targets,
                                  surrogate.predict, to_params, log=lambda m: None, surrogate=surrogate)
    np.testing.assert_allclose([r["theta"] for r in rows], b.theta)
    assert metrics["npe_pen"]["uncertainty_penalty"] == 100.0
    with pytest.raises(InvphysError, match="uncertainty_penalty needs a surrogate with uncertainty"):
        baseline_rows({"npe_pen": fitted}, theta, y, scales, targets, surrogate.predict, to_params,
                      log=lambda m: None)


def test_npe_writes_nothing_into_the_working_directory(tmp_path, monkeypatch) -> None:
    theta, y = _hidden_parameter_problem(100)
    monkeypatch.chdir(tmp_path)
    NPEBaseline(estimator="mdn", hidden_features=8, max_num_epochs=2).fit(theta, y, percentile_scales(y))
    assert list(tmp_path.iterdir()) == []  # sbi's default tracker would write ./sbi-logs


@pytest.mark.parametrize("estimator,transform", [("maf", "none"), ("nsf", "logit"), ("mdn", "none")])
def test_npe_saves_tensors_and_rebuilds_the_same_posterior_without_unpickling(estimator, transform,
                                                                              tmp_path) -> None:
    """The saved flow is an .npz of tensors plus a JSON architecture; the posterior rebuilt from code gives
    bit-identical samples and log-probs (same seed) to the trained one, and no file is a pickle."""
    theta, y = _hidden_parameter_problem(160)
    npe = NPEBaseline(estimator=estimator, transform=transform, hidden_features=8, num_transforms=2,
                      max_num_epochs=3, training_batch_size=32, samples=16, seed=2)
    npe.fit(theta, y, percentile_scales(y))
    npe.save(tmp_path / "npe")
    assert sorted(p.name for p in (tmp_path / "npe").iterdir()) == ["npe.json", "npe_weights.npz"]
    with np.load(tmp_path / "npe" / "npe_weights.npz", allow_pickle=False) as z:
        assert all(z[k].dtype.kind in "fi" for k in z.files)
    again = NPEBaseline.load(tmp_path / "npe")
    s0, lp0 = npe.posterior_samples(y[:7])
    s1, lp1 = again.posterior_samples(y[:7])
    np.testing.assert_array_equal(s1, s0)
    np.testing.assert_array_equal(lp1, lp0)
    np.testing.assert_array_equal(again._scales, npe._scales)
    import torch

    box = torch.tensor([[0.5, 0.5], [1.0, 0.0], [1.2, 0.5], [float("nan"), 0.5]])  # the prior's support is kept
    np.testing.assert_array_equal(again._posterior.prior.support.check(box).numpy(),
                                  npe._posterior.prior.support.check(box).numpy())


def test_npe_refuses_pickles_wrong_shapes_and_an_older_pickled_save(npe_fitted, tmp_path) -> None:
    import pickle

    import torch

    from invphys.models.base import LegacyPickleError

    d = npe_fitted.save(tmp_path / "npe")
    weights = d / "npe_weights.npz"
    good = weights.read_bytes()
    weights.write_bytes(pickle.dumps({"a": np.zeros(3)}))  # a pickle where the tensors belong
    with pytest.raises(InvphysError, match=r"npe_weights\.npz: not a weights archive"):
        NPEBaseline.load(d)
    with weights.open("wb") as fh:  # an object array inside (np.load runs pickle for those)
        np.savez(fh, boom=np.array([object()], dtype=object))
    with pytest.raises(InvphysError, match=r"npe_weights\.npz: not a weights archive"):
        NPEBaseline.load(d)
    weights.write_bytes(good)
    with np.load(weights) as z:
        arrays = {k: z[k] for k in z.files}
    key = next(k for k, v in arrays.items() if v.ndim == 2)
    arrays[key] = np.zeros((3, 3), np.float32)
    with weights.open("wb") as fh:
        np.savez(fh, **arrays)
    with pytest.raises(InvphysError, match=rf"do not fit the saved architecture \({key} has shape \(3, 3\)"):
        NPEBaseline.load(d)
    weights.write_bytes(good)
    meta = json.loads((d / "npe.json").read_text())  # a description far larger than the weights: never built
    (d / "npe.json").write_text(json.dumps({**meta, "config": {**meta["config"], "hidden_features": 10**6}}))
    with pytest.raises(InvphysError, match=r"hidden_features 1000000.* does not fit the [0-9,]+ saved numbers"):
        NPEBaseline.load(d)
    (d / "npe.json").write_text(json.dumps(meta))
    # an older save: the posterior pickled in npe.pt is refused, loaded only by the explicit legacy call
    weights.unlink()
    torch.save({"posterior": npe_fitted._posterior, "scales": npe_fitted._scales, "metrics": {}}, d / "npe.pt")
    with pytest.raises(LegacyPickleError, match=r"npe\.pt is a pickled object"):
        NPEBaseline.load(d)
    legacy = NPEBaseline.load_legacy_pickle(d)
    legacy.save(d)  # writes the tensor format and removes npe.pt
    assert not (d / "npe.pt").exists()
    np.testing.assert_array_equal(NPEBaseline.load(d).posterior_samples(np.zeros((2, 2)))[0],
                                  npe_fitted.posterior_samples(np.zeros((2, 2)))[0])
