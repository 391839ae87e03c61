"""A pool answer that is a stored row of the bundle reports its REAL features and their R against the
target (``known``, ``r_known``: simulated when the bundle's data was made), next to the surrogate's R;
its spread is zero. Shipped paper bundle, a private copy."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_inverter_support import paper_inverter

from invphys.core.masked_recovery import masked_recovery


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    return paper_inverter(tmp_path_factory.getbasetemp())


def _pool(inv, targets, **settings):
    from invphys.inverter.pool import PoolSettings

    inv.pool_settings = PoolSettings().with_(**settings)
    try:
        return inv.invert_many(targets, method="pool", seed=0, draws=64, top_k=4, partial=True)
    finally:
        inv.pool_settings = PoolSettings()


def _row_of(theta_all, theta):
    hits = np.flatnonzero(np.all(theta_all == theta, axis=1))
    return int(hits[0]) if len(hits) else None


def test_a_training_row_answer_reports_its_real_r(inv) -> None:
    """Targets that ARE training rows, with exact: the answer is the row, R_known 1 (its own features),
    while the surrogate's R there is below 0.99; its known features are the row's, its spread zero."""
    theta, y = inv.bundle.data("train")
    rows = [3, 41, 500]
    for i, r in zip(rows, _pool(inv, y[rows], exact=True), strict=True):
        best = r.candidates[0]
        np.testing.assert_array_equal(best.theta, theta[i])
        np.testing.assert_array_equal(best.known, y[i])
        assert r.r_known == pytest.approx(1.0) and best.r_surrogate < 0.99
        assert not best.spread.any() and best.std.any()  # the ensemble's std stays what it is
        assert isinstance(best.source, str) and type(best.source) is str
        data = r.to_dict()["candidates"][0]
        assert data["r_known"] == pytest.approx(1.0)
        assert [f["known"] for f in data["features"].values()] == pytest.approx(list(y[i]))
        json.dumps(r.to_dict())


def test_every_stored_candidate_knows_its_r_and_others_do_not(inv) -> None:
    """Default pool (stored rows scored by the surrogate): every candidate that is a stored row carries
    the exact R of its real features over the GIVEN features (a partial target too); draws and moves
    carry none."""
    theta, y = inv.bundle.data("train")
    _, targets = inv.bundle.data("test")
    partial = [dict(zip(inv.feature_names, map(float, t), strict=True)) for t in targets[:20]]
    for t in partial[10:]:
        del t["peeling_work"]
    seen = {"known": 0, "other": 0}
    for res in _pool(inv, partial, neighbours=32, draws=2, moves=2):  # stored rows among the top 4
        for c in res.candidates:
            j = _row_of(theta, c.theta)
            if c.source.endswith("(neighbour)"):
                assert j is not None
                want = masked_recovery(y[j][None], res.target, inv.bundle.scales, res.mask, inv.bundle.kappa)[0]
                assert c.r_known == pytest.approx(float(want), abs=1e-12)
                np.testing.assert_array_equal(c.known, y[j])
                seen["known"] += 1
            else:
                assert c.known is None and c.r_known is None
                seen["other"] += 1
        for c, data in zip(res.candidates, res.to_dict()["candidates"], strict=True):
            assert ("r_known" in data) == (c.known is not None)
    assert seen["known"] and seen["other"]


def test_a_noisy_target_measures_a_stored_row_by_its_real_features(inv) -> None:
    """chi2 of a stored-row answer uses its real features and no ensemble spread."""
    _, y = inv.bundle.data("train")
    target = dict(zip(inv.feature_names, map(float, y[41]), strict=True))
    res = _pool(inv, [target], exact=True)[0]
    std = np.full(len(inv.feature_names), 0.05) * inv.bundle.scales
    res.target_std = std
    assert res.r_known == pytest.approx(1.0)
    assert res.chi2() == pytest.approx(0.0, abs=1e-20)
    res.candidates[0].known = None  # the prediction instead: misfit > 0
    assert res.chi2() > 0


def test_a_lookup_answer_is_a_stored_row_and_says_so(inv) -> None:
    """The nearest-neighbour lookup answers with training rows: each carries its real features and R
    (a target that is a training row: that row, R_known 1, above its R_surr)."""
    theta, y = inv.bundle.data("train")
    for i, r in zip([3, 41], inv.invert_many(y[[3, 41]], method="lookup"), strict=True):
        np.testing.assert_array_equal(r.theta, theta[i])
        np.testing.assert_array_equal(r.candidates[0].known, y[i])
        assert r.r_known == pytest.approx(1.0) and r.r_surrogate < 0.99
    _, targets = inv.bundle.data("test")
    for r in inv.invert_many(targets[:5], method="lookup"):
        for c in r.candidates:
            j = _row_of(theta, c.theta)
            assert j is not None
            want = masked_recovery(y[j][None], r.target, inv.bundle.scales, None, inv.bundle.kappa)[0]
            assert c.r_known == pytest.approx(float(want), abs=1e-12)


def test_the_terminal_shows_a_stored_rows_real_r(inv, tmp_path) -> None:
    """`invphys invert` prints R_known for a stored-row answer (a training row's own features: R_known 1.000)
    and nothing of the kind for an answer the surrogate alone scored."""
    from typer.testing import CliRunner

    from invphys.cli import app

    _, y = inv.bundle.data("train")
    names = inv.bundle.feature_names
    target = tmp_path / "t.json"
    target.write_text(json.dumps({n: float(v) for n, v in zip(names, y[3], strict=True)}))
    res = CliRunner().invoke(app, ["invert", str(inv.bundle.root), "-t", str(target), "--method", "lookup"])
    assert res.exit_code == 0, res.output
    assert "R_known 1.000 (a stored row" in res.output
    res = CliRunner().invoke(app, ["invert", str(inv.bundle.root), "-t", str(target), "--method", "cma_es_540"])
    assert res.exit_code == 0, res.output
    assert "R_known" not in res.output


def test_stored_rows_travel_as_data_beside_plain_string_sources(inv) -> None:
    """The answer protocol carries a stored row's real features as data (``Pool.known``, row for row), not
    inside its source string: every source is a plain ``str``, and candidates made from sources rebuilt
    from text (here read back from JSON, which kept nothing but the text) still know their rows."""
    from invphys.inverter.answers import Known, Pool
    from invphys.inverter.pool import PoolSettings

    theta, y = inv.bundle.data("train")
    mask = np.ones(y.shape[1], bool)
    inv.pool_settings = PoolSettings().with_(exact=True)
    try:
        pool, _ = inv._answers("pool", inv._entry("pool")[1]).answer(y[41], mask, 8, 0, 64)
    finally:
        inv.pool_settings = PoolSettings()
    assert isinstance(pool, Pool) and pool.known is not None
    assert len(pool.known) == len(pool.sources) == len(pool.thetas)
    for src, k, t in zip(pool.sources, pool.known, pool.thetas, strict=True):
        assert type(src) is str and (k is not None) == src.endswith("(neighbour)")
        if k is not None:
            j = _row_of(theta, t)
            assert isinstance(k, Known) and j is not None
            np.testing.assert_array_equal(k.features, y[j])
            want = masked_recovery(y[j][None], y[41], inv.bundle.scales, mask, inv.bundle.kappa)[0]
            assert k.r == pytest.approx(float(want), abs=1e-12)
    texts = json.loads(json.dumps(pool.sources))
    cands = inv._candidates(pool.thetas, texts, y[41], mask, pool.known)
    np.testing.assert_array_equal(cands[0].theta, theta[41])  # the row itself, best by its real R
    np.testing.assert_array_equal(cands[0].known, y[41])
    assert cands[0].r_known == pytest.approx(1.0) and cands[0].source == "pool (neighbour)"
    assert [c.known is None for c in cands] == [k is None for k in pool.known]
    lookup, _ = inv._answers("lookup", inv._entry("lookup")[1]).answer(y[3], mask, 1, 0, 1)
    assert lookup.sources == ["lookup"] and lookup.known is not None and lookup.known[0] is not None
    np.testing.assert_array_equal(lookup.known[0].features, y[3])
