"""An answer is a function of (bundle, target, method, seed): never of the target's position, its batch,
or the other targets (shipped paper bundle, a private copy)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_inverter_support import paper_inverter


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    return paper_inverter(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def rows(inv):
    """1,000 distinct targets: held-out rows, then training rows."""
    _, y_test = inv.bundle.data("test")
    _, y_train = inv.bundle.data("train")
    return np.concatenate([y_test, y_train])[:1000]


def _same(a, b) -> None:
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.theta, y.theta)
        assert x.r_surrogate == y.r_surrogate  # labels of unlabelled rows are their positions
        ux, uy = x.parameter_uncertainty, y.parameter_uncertainty
        assert ux.kind == uy.kind
        if ux.draws is not None:
            np.testing.assert_array_equal(ux.draws, uy.draws)


@pytest.mark.parametrize("method", ["lookup", "gc_ppo_vae"])
def test_fast_methods_answer_a_target_alike_alone_or_in_a_batch_of_1000(inv, rows, method) -> None:
    labels = [f"r{i}" for i in range(len(rows))]
    targets = [dict(zip(inv.feature_names, map(float, r), strict=True), label=lb) for r, lb in zip(rows, labels,
                                                                                                  strict=True)]
    batch = inv.invert_many(targets, method=method, seed=5)
    order = np.random.default_rng(0).permutation(len(rows))
    shuffled = inv.invert_many([targets[i] for i in order], method=method, seed=5)
    _same([batch[i] for i in order], shuffled)
    _same(batch[::-1], inv.invert_many(targets[::-1], method=method, seed=5))
    for i in (0, 377, 999):
        _same([batch[i]], [inv.invert(targets[i], method=method, seed=5)])


def test_npe_draws_and_answers_depend_on_the_target_and_the_seed_only(inv, rows) -> None:
    """Before, each row drew from the stream of its position and --seed was ignored."""
    some = rows[:10]
    batch = inv.invert_many(some, seed=1)
    assert batch[0].method == "npe_best64" and batch[0].posterior == "posterior"
    _same(batch[::-1], inv.invert_many(some[::-1], seed=1))
    _same([batch[4]], inv.invert_many(np.concatenate([rows[500:503], some[4:5]]), seed=1)[3:])
    other = inv.invert_many(some, seed=2)
    assert all(not np.array_equal(a.parameter_uncertainty.draws, b.parameter_uncertainty.draws)
               for a, b in zip(batch, other, strict=True))
    # the public draws API gives the answers' draws (recalibrated as the bundle's diagnostics say); the
    # posterior's own draws are prefix-stable in n
    np.testing.assert_array_equal(inv.posterior(some[:3], n=256, seed=1).samples,
                                  np.stack([r.parameter_uncertainty.draws for r in batch[:3]]))
    d = inv.posterior(some[:3], n=300, seed=1, recalibrate=False)
    np.testing.assert_array_equal(d.samples[:, :256], inv.posterior(some[:3], n=256, seed=1, recalibrate=False).samples)
    np.testing.assert_array_equal(inv.posterior(some[2], n=40, seed=1, recalibrate=False).samples[0], d.samples[2, :40])
    assert d.samples.shape == (3, 300, 9) and d.samples.min() >= 0 and d.samples.max() <= 1


def test_a_posterior_answer_does_not_depend_on_the_intervals_draws(inv) -> None:
    """A held-out target whose posterior lies almost wholly outside the box (~99 % of raw draws rejected, so a
    run stops at its cap with clipped draws): its answer is the same for 1, 64, 256 or 1,000 interval draws
    and through invert_array (the cap grows with a run's length, and the answer used to follow it)."""
    _, y = inv.bundle.data("test")
    t = y[112][None, :]
    assert inv.posterior(t, n=64, method="npe_best64").clipped[0] > 0  # the case this test is about
    answers = [inv.invert_many(t, method="npe_best64", draws=d)[0].theta for d in (1, 64, 256, 1000)]
    for theta in answers[1:]:
        np.testing.assert_array_equal(theta, answers[0])
    np.testing.assert_array_equal(inv.invert_array(t, method="npe_best64")[0], answers[0])
    pool = [inv.invert_many(t, method="pool", draws=d)[0].theta for d in (1, 1000)]
    np.testing.assert_array_equal(pool[0], pool[1])


def test_searches_and_refine_are_seeded_by_the_target(inv, rows) -> None:
    a = inv.invert_many(rows[:2], method="cma_es_540", seed=3, refine=20, top_k=2)
    b = inv.invert_many(rows[:2][::-1], method="cma_es_540", seed=3, refine=20, top_k=2)[::-1]
    for x, y in zip(a, b, strict=True):
        assert [c.source for c in x.candidates] == [c.source for c in y.candidates]
        for cx, cy in zip(x.candidates, y.candidates, strict=True):
            np.testing.assert_array_equal(cx.theta, cy.theta)
    c = inv.invert(rows[0], method="cma_es_540", seed=4)
    assert not np.array_equal(c.theta, a[0].theta)


def test_cli_json_parses_for_every_method(inv, rows, tmp_path) -> None:
    """stdout holds only JSON (sbi's training and sampling prints went there before)."""
    from typer.testing import CliRunner

    from invphys.cli import app

    f = tmp_path / "targets.json"
    f.write_text(json.dumps([dict(zip(inv.feature_names, map(float, r), strict=True)) for r in rows[:2]]))
    for method in inv.methods:
        args = ["invert", str(inv.bundle.root), "--target", str(f), "--json", "--method", method]
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 0, res.output
        data = json.loads(res.stdout)
        assert data["method"] == method and len(data["results"]) == 2
        post = data["results"][0]["posterior"]
        assert (post is not None) == (method in ("npe_best64", "pool")), method


def test_third_party_prints_and_warnings_go_to_the_log(caplog, capsys) -> None:
    import logging
    import warnings

    from invphys.inverter.quiet import quiet

    with caplog.at_level(logging.DEBUG, logger="invphys.thirdparty"), quiet():
        print(" Neural network successfully converged after 20 epochs.")
        warnings.warn("Capping max_sampling_batch_size", UserWarning, stacklevel=1)
    assert capsys.readouterr().out == ""
    text = caplog.text
    assert "successfully converged" in text and "Capping max_sampling_batch_size" in text
