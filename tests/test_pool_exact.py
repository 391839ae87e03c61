"""The candidate pool with ``exact``: stored rows scored by their real features (the R they really reach,
no penalty), surrogate-scored candidates less a ``margin``, and ``rows="all"`` (the bundle's held-out
rows offered too). Shipped paper bundle, a private copy."""

from __future__ import annotations

import numpy as np
import pytest
from test_inverter_support import paper_inverter

from invphys.core.errors import InvphysError
from invphys.core.masked_recovery import masked_recovery


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    return paper_inverter(tmp_path_factory.getbasetemp())


def _pool(inv, targets, seed=0, draws=None, **settings):
    from invphys.inverter.pool import PoolSettings

    inv.pool_settings = PoolSettings().with_(**settings)
    try:
        kw = {} if draws is None else {"draws": draws}
        return inv.invert_many(targets, method="pool", seed=seed, **kw)
    finally:
        inv.pool_settings = PoolSettings()


def _surrogate_r(inv, theta, target):
    return masked_recovery(inv.bundle.surrogate.predict(np.atleast_2d(theta)), target, inv.bundle.scales, None,
                           inv.bundle.kappa)


def test_a_stored_row_is_scored_by_its_real_features(inv) -> None:
    """Targets that are training rows: scored exactly, the row itself reaches R = 1 and is the answer;
    scored by the surrogate (the old pool) it is not, because the surrogate is off there."""
    theta, y = inv.bundle.data("train")
    rows = [3, 41, 500, 977, 2024]
    exact = _pool(inv, y[rows], exact=True)
    plain = _pool(inv, y[rows])
    for i, e in zip(rows, exact, strict=True):
        np.testing.assert_array_equal(e.theta, theta[i])
        assert e.candidates[0].source == "pool (neighbour)"
    assert sum(not np.array_equal(p.theta, theta[i]) for i, p in zip(rows, plain, strict=True)) >= 3
    # the surrogate's own R of those rows is below 1: the bias the exact score removes
    assert all(float(_surrogate_r(inv, theta[i], y[i])[0]) < 0.99 for i in rows)


def test_the_answer_is_the_best_of_exact_rows_and_surrogate_candidates_less_the_margin(inv) -> None:
    """No moves and no penalty: the answer's score is max(R_surr(draws) - margin, exact R(neighbours)),
    and the choice flips from a draw to a stored row as the margin grows."""
    from invphys.inverter.pool import nearest_rows

    _, targets = inv.bundle.data("test")
    targets = targets[:12]
    answers = inv._answers("pool", inv._entry("pool")[1])
    full = np.ones(targets.shape[1], bool)
    kinds = {}
    for margin in (0.0, 0.05, 0.9):
        res = _pool(inv, targets, draws=64, exact=True, margin=margin, moves=0, lam=0.0)
        draws = inv.posterior(targets, n=64, method="pool", recalibrate=False).samples
        for t, r, d in zip(targets, res, draws, strict=True):
            near = nearest_rows(answers.z_train, t, full, inv.bundle.scales, 16)
            exact = masked_recovery(answers.train_y[near], t, inv.bundle.scales, None, inv.bundle.kappa)
            best = max(float(_surrogate_r(inv, d, t).max()) - margin, float(exact.max()))
            got = float(exact[0]) if r.candidates[0].source.endswith("(neighbour)") else \
                float(_surrogate_r(inv, r.theta, t)[0]) - margin
            assert got == pytest.approx(best, abs=1e-6)  # float32 surrogate, other batch shapes
        kinds[margin] = [r.candidates[0].source.endswith("(neighbour)") for r in res]
    assert sum(kinds[0.0]) < sum(kinds[0.9]) == len(targets)  # a margin near 1: the 1-NN lookup by R
    lookup = _pool(inv, targets, exact=True, margin=0.9, moves=0)
    for t, r in zip(targets, lookup, strict=True):
        np.testing.assert_array_equal(r.theta, answers.train_theta[nearest_rows(answers.z_train, t, full,
                                                                                inv.bundle.scales, 1)[0]])


def test_rows_all_offers_the_held_out_rows(inv) -> None:
    theta, y = inv.bundle.data("test")
    rows = [0, 5, 9]
    with_heldout = _pool(inv, y[rows], exact=True, rows="all")
    train_only = _pool(inv, y[rows], exact=True)
    for i, a, b in zip(rows, with_heldout, train_only, strict=True):
        np.testing.assert_array_equal(a.theta, theta[i])
        assert not np.array_equal(b.theta, theta[i])


def test_exact_pool_answers_depend_on_the_target_alone(inv) -> None:
    _, y = inv.bundle.data("test")
    targets = y[:30]
    kw = {"exact": True, "margin": 0.05, "rows": "all", "seed": 4}
    batch = _pool(inv, targets, **kw)
    order = np.random.default_rng(2).permutation(len(targets))
    shuffled = _pool(inv, targets[order], **kw)
    reverse = _pool(inv, targets[::-1], **kw)
    for i, j in enumerate(order):
        np.testing.assert_array_equal(batch[j].theta, shuffled[i].theta)
    for i in range(len(targets)):
        np.testing.assert_array_equal(batch[i].theta, reverse[len(targets) - 1 - i].theta)
    np.testing.assert_array_equal(_pool(inv, targets[7:8], **kw)[0].theta, batch[7].theta)


def test_a_bundle_method_entry_carries_the_exact_settings(inv) -> None:
    theta, y = inv.bundle.data("train")
    methods = inv.bundle.methods
    methods["pool_exact"] = {"type": "pool", "kind": "pool", "space": "raw", "evaluator": "shared",
                             "config": {"exact": True, "margin": 0.05, "rows": "all"}}
    try:
        res = inv.invert(y[11], method="pool_exact")
        np.testing.assert_array_equal(res.theta, theta[11])
    finally:
        methods.pop("pool_exact")


@pytest.mark.parametrize("bad", [{"exact": "yes"}, {"exact": 1.0}, {"margin": 0.05}, {"exact": True, "margin": 1.0},
                                 {"exact": True, "margin": -0.1}, {"rows": "everything"}, {"rows": 3},
                                 {"anchor": True}, {"exact": True, "anchor": "no"}])
def test_bad_exact_settings_are_refused(bad) -> None:
    from invphys.inverter.pool import PoolSettings

    with pytest.raises(InvphysError, match="pool"):
        PoolSettings().with_(**bad)


def test_anchored_moves_from_a_stored_row_carry_its_residual(inv) -> None:
    """A target that is a training row: the row scores 1 and is the only start; with ``anchor`` every move
    is ranked by R(f(theta') + y_j - f(theta_j)), without it by R(f(theta'))."""
    theta, y = inv.bundle.data("train")
    j = 41
    resid = y[j] - inv.bundle.surrogate.predict(theta[j:j + 1])[0]

    def moves(anchor):
        from invphys.inverter.pool import PoolSettings

        inv.pool_settings = PoolSettings().with_(exact=True, anchor=anchor, starts=1, lam=0.0)
        try:
            answers = inv._answers("pool", inv._entry("pool")[1])
            (thetas, sources, _, _), _ = answers.answer(y[j], np.ones(y.shape[1], bool), 112, 0, 64)
        finally:
            inv.pool_settings = PoolSettings()
        np.testing.assert_array_equal(thetas[0], theta[j])  # the pool's own order: best first
        return thetas[[i for i, src in enumerate(sources) if src.endswith("(move)")]]

    def r(thetas, offset):
        pred = inv.bundle.surrogate.predict(thetas) + offset
        return masked_recovery(pred, y[j], inv.bundle.scales, None, inv.bundle.kappa)

    anchored, plain = moves(True), moves(False)
    np.testing.assert_array_equal(np.sort(anchored, axis=0), np.sort(plain, axis=0))  # the same moves
    assert np.all(np.diff(r(anchored, resid)) <= 1e-6)  # ranked by the anchored prediction
    assert np.all(np.diff(r(plain, 0.0)) <= 1e-6)
    assert not np.array_equal(anchored, plain)  # and the two rankings differ
    assert r(anchored, resid).mean() > r(plain, 0.0).mean()  # near the row, its residual brings R towards 1
