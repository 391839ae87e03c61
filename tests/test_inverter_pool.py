"""The candidate pool (``method="pool"``): posterior draws, nearest training rows and local moves scored by
the ensemble with an uncertainty penalty; and posterior draws made for many targets at once that are
bit-for-bit those of each target alone (shipped paper bundle, a private copy)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_inverter_support import paper_inverter

from invphys.core.errors import InvphysError


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    return paper_inverter(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def rows(inv):
    _, y = inv.bundle.data("test")
    return y[:40]


def _penalised(inv, theta, target, lam):
    from invphys.core.masked_recovery import masked_recovery
    from invphys.evaluators.uncertainty import normalised_std

    mean, std = inv.bundle.surrogate.predict_with_uncertainty(np.atleast_2d(theta))
    r = masked_recovery(mean, target, inv.bundle.scales, None, inv.bundle.kappa)
    return r - lam * normalised_std(std, inv.bundle.scales)


def test_pool_is_a_method_of_a_bundle_with_a_posterior(inv, rows) -> None:
    assert "pool" in inv.methods
    res = inv.invert(rows[0], method="pool")
    assert res.method == "pool" and res.posterior == "posterior"
    assert res.candidates[0].source in ("pool (posterior)", "pool (neighbour)", "pool (move)")
    # its draws are the NPE's own (same per-target stream), so its intervals are the NPE's
    np.testing.assert_array_equal(inv.posterior(rows[:2], n=50, method="pool").samples,
                                  inv.posterior(rows[:2], n=50, method="npe_best64").samples)


def test_pool_of_the_draws_alone_is_the_npe_answer(inv, rows) -> None:
    """With no neighbours, no moves and no penalty the pool is the NPE's best of its 64 draws."""
    from invphys.inverter.pool import PoolSettings

    inv.pool_settings = PoolSettings(neighbours=0, moves=0, lam=0.0)
    try:
        a = inv.invert_many(rows[:6], method="pool", seed=2)
    finally:
        inv.pool_settings = PoolSettings()
    b = inv.invert_many(rows[:6], method="npe_best64", seed=2)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.theta, y.theta)


def test_the_pool_scores_at_least_as_well_as_its_parts(inv, rows) -> None:
    """The answer is the best penalised candidate of draws + neighbours + moves: never below the NPE's
    answer or the nearest training row by the same score."""
    from invphys.inverter.pool import PoolSettings, nearest_rows

    lam = PoolSettings().lam
    pool = inv.invert_many(rows[:8], method="pool")
    npe = inv.invert_many(rows[:8], method="npe_best64")
    answers = inv._answers("pool", inv._entry("pool")[1])
    sources = set()
    for p, n, y in zip(pool, npe, rows[:8], strict=True):
        near = answers.train_theta[nearest_rows(answers.z_train, y, np.ones(len(y), bool), inv.bundle.scales, 1)]
        best = float(_penalised(inv, p.theta, y, lam)[0])
        assert best >= float(_penalised(inv, n.theta, y, lam)[0]) - 1e-12
        assert best >= float(_penalised(inv, near, y, lam)[0]) - 1e-12
        sources.add(p.candidates[0].source)
    assert "pool (move)" in sources  # the local moves improve on the draws and rows for some target


def test_a_larger_penalty_keeps_the_answer_where_the_ensemble_agrees(inv, rows) -> None:
    from invphys.evaluators.uncertainty import normalised_std
    from invphys.inverter.pool import PoolSettings

    def spread(lam):
        inv.pool_settings = PoolSettings(lam=lam)
        try:
            res = inv.invert_many(rows[:10], method="pool")
        finally:
            inv.pool_settings = PoolSettings()
        _, std = inv.bundle.surrogate.predict_with_uncertainty(np.array([r.theta for r in res]))
        return normalised_std(std, inv.bundle.scales)  # the ensemble's own spread (shown bars may be calibrated)

    loose, tight = spread(0.0), spread(20.0)
    assert np.all(tight <= loose + 1e-12) and np.any(tight < loose)


def test_pool_answers_depend_on_the_target_alone(inv) -> None:
    """Shuffled, reversed, alone, or among partial targets: the same answers and draws (130 targets:
    several batches of draws made together, each flow call several blocks of rounds)."""
    _, y = inv.bundle.data("test")
    targets = [dict(zip(inv.feature_names, map(float, r), strict=True)) for r in y[:125]]
    partial = [{k: v for k, v in t.items() if k not in ("fracture_onset_frame", "peeling_work")} for t in targets[:5]]
    every = targets + partial
    kw = {"method": "pool", "seed": 7, "partial": True, "draws": 64}
    batch = inv.invert_many(every, **kw)
    order = np.random.default_rng(1).permutation(len(batch))
    shuffled = inv.invert_many([every[i] for i in order], **kw)
    for i, j in enumerate(order):
        np.testing.assert_array_equal(batch[j].theta, shuffled[i].theta)
        np.testing.assert_array_equal(batch[j].parameter_uncertainty.draws, shuffled[i].parameter_uncertainty.draws)
    for i in (0, 77, len(targets) + 2):
        alone = inv.invert(every[i], **kw)
        np.testing.assert_array_equal(batch[i].theta, alone.theta)
        np.testing.assert_array_equal(batch[i].parameter_uncertainty.draws, alone.parameter_uncertainty.draws)
    assert not np.array_equal(inv.invert(targets[0], **{**kw, "seed": 8}).theta, batch[0].theta)


def test_draws_made_together_are_those_made_alone(inv, rows) -> None:
    """The flow runs on blocks of whole rounds for many targets at once; every target's draws equal
    sbi's own sample() under its seed, target by target (complete and partial targets)."""
    from invphys.inverter import draws as D

    plugin = inv._plugin("npe_best64", inv._entry("npe_best64")[1])[0]
    est = plugin._posterior.posterior_estimator
    assert D._flow(est) is not None
    mean = np.asarray(inv.bundle.manifest["features"]["mean"])
    full = np.ones(rows.shape[1], bool)
    part = full.copy()
    part[[2, 5, 9]] = False
    train_y = inv.bundle.data("train")[1]
    conds = [D.completions(v, full, None, mean, inv.bundle.scales) for v in rows[:20]]
    conds += [D.completions(v, part, train_y, mean, inv.bundle.scales) for v in rows[20:24]]
    seeds = list(range(50, 74))
    together = D._together(D._flow(est), conds, seeds, 300, False)
    for i in (0, 7, 19, 21):
        alone = D._one(est, conds[i], seeds[i], 300, False)
        np.testing.assert_array_equal(together[i][0], alone[0])
        assert together[i][1:] == alone[1:]


@pytest.mark.parametrize("bad", [{"draws": 0}, {"step": 0.0}, {"lam": -1.0}, {"moves": 1.5}, {"step": "x"},
                                 {"lam": float("nan")}])
def test_bad_pool_settings_are_refused(inv, bad) -> None:
    from invphys.inverter.pool import PoolSettings

    with pytest.raises(InvphysError, match="pool"):
        PoolSettings().with_(**bad)


def test_cli_answers_with_the_pool(inv, rows, tmp_path) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    f = tmp_path / "targets.json"
    f.write_text(json.dumps([dict(zip(inv.feature_names, map(float, r), strict=True)) for r in rows[:2]]))
    res = CliRunner().invoke(app, ["invert", str(inv.bundle.root), "--target", str(f), "--json", "--method", "pool"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert data["method"] == "pool" and data["results"][0]["posterior"] is not None


@pytest.fixture()
def second_npe(inv):
    """A second posterior method (the same saved flow under another label: its own per-target stream)."""
    methods = inv.bundle.methods
    methods["npe_b"] = dict(methods["npe_best64"])
    try:
        yield "npe_b"
    finally:
        methods.pop("npe_b")
        inv._plugins.pop("npe_b", None)


def test_an_ensemble_pool_joins_the_draws_of_every_member(inv, rows, second_npe) -> None:
    """``extra`` adds each member's draws (its own per-target stream) to the pool: with no moves and no
    penalty the answer is the best by the surrogate of both members' draws and the nearest rows."""
    from invphys.inverter.pool import PoolSettings, nearest_rows

    base = PoolSettings(moves=0, lam=0.0)
    inv.pool_settings = base.with_(extra=[second_npe])
    try:
        assert inv.pool_settings.extra == (second_npe,)
        ens = inv.invert_many(rows[:6], method="pool", seed=3, draws=64)
    finally:
        inv.pool_settings = PoolSettings()
    own = inv.posterior(rows[:6], n=64, seed=3, method="npe_best64", recalibrate=False).samples
    member = inv.posterior(rows[:6], n=64, seed=3, method=second_npe, recalibrate=False).samples
    assert not np.array_equal(own, member)
    theta, y = inv.bundle.data("train")
    z = y / np.maximum(inv.bundle.scales, 1e-12)
    full = np.ones(rows.shape[1], bool)
    wins = 0
    for i, res in enumerate(ens):
        near = theta[nearest_rows(z, rows[i], full, inv.bundle.scales, base.neighbours)]
        union = np.concatenate([own[i], member[i], near])
        r = _penalised(inv, union, rows[i], 0.0)
        np.testing.assert_allclose(_penalised(inv, res.theta, rows[i], 0.0)[0], r.max(), rtol=1e-6)
        wins += int(np.argmax(r) in range(64, 128))
    assert wins  # the member's draws do win some targets


def test_an_extra_posterior_that_is_not_one_is_refused(inv, rows) -> None:
    from invphys.inverter.pool import PoolSettings

    with pytest.raises(InvphysError, match="extra"):
        PoolSettings().with_(extra=[3])
    inv.pool_settings = PoolSettings(extra=("lookup_nowhere",))
    try:
        with pytest.raises(InvphysError, match="lookup_nowhere"):
            inv.invert(rows[0], method="pool")
    finally:
        inv.pool_settings = PoolSettings()


def test_nearest_rows_break_ties_by_the_lower_row_index() -> None:
    """Rows as near as the k-th are ranked by index, as a stable sort would (duplicate stored rows: the
    neighbours, and so the pool's answers, must not depend on how a partial sort happens to split ties)."""
    from invphys.inverter.pool import nearest_rows

    rng = np.random.default_rng(0)
    z = rng.integers(0, 3, size=(400, 2)).astype(float)   # many exact ties
    z[5] = np.nan                                          # a row with a missing feature: never near
    scales, mask = np.ones(2), np.ones(2, bool)
    for target in (np.array([1.0, 1.0]), np.array([0.0, 2.0])):
        d2 = ((z - target) ** 2).sum(1)
        want = np.argsort(np.where(np.isfinite(d2), d2, np.inf), kind="stable")
        for k in (1, 7, 16, 45, 400):
            assert nearest_rows(z, target, mask, scales, k).tolist() == want[:k].tolist()
