"""The ``corrected`` simulator refine (surrogate corrected by the target's own runs) and known starts, on the toy.

Real components: the toy bundle, its oscillator simulator and the refine stream. A biased surrogate (the
toy's own, plus a smooth error) is where the correction must pay: the same strategy with the correction
switched off, and CMA-ES at the same budget, end lower.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from test_inverter_refine import ShuffledToy
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)

from invphys.core.errors import InvphysError
from invphys.inverter.refine import refine
from invphys.inverter.simulate import masked_score


def _key(res) -> list[tuple]:
    return [(tuple(r.best.theta), r.best.r_actual, r.best.source) for r in res]


def _run(inv, y, budget=12, **kw):
    res = inv.invert_many(y, top_k=3)
    recs = refine(inv, res, budget, popsize=4, strategy="corrected", **kw)
    return res, recs


def test_corrected_answers_do_not_depend_on_order_batch_size_or_completion(inv) -> None:
    _, y = inv.bundle.data("test")
    ref, recs = _run(inv, y[:5], batch_size=1)
    for r, rec in zip(ref, recs, strict=True):   # never worse than the best start (known starts included)
        assert rec["runs"] == 12 and rec["known_starts"] == 8
        assert r.best.r_actual == rec["r_actual"] >= rec["start_r_actual"]
    assert sum(rec["r_actual"] > rec["start_r_actual"] for rec in recs) >= 2   # the search finds better points
    assert _key(_run(inv, y[:5], batch_size=7)[0]) == _key(ref)
    assert _key(_run(inv, y[:5][::-1], batch_size=3)[0])[::-1] == _key(ref)
    assert _key(_run(inv, y[3:4])[0]) == _key(ref[3:4])
    shuffled = ShuffledToy(inv.simulator().config)
    shuffled.order_seed = 3
    assert _key(_run(inv, y[:5], batch_size=4, simulator=shuffled)[0]) == _key(ref)


def test_known_starts_cost_no_runs_and_are_the_best_stored_rows(inv) -> None:
    _, y = inv.bundle.data("test")
    train_theta, train_y = inv.bundle.data("train")
    res, recs = _run(inv, y[:4], budget=3, known_starts=5)
    score = masked_score(inv)
    for r, rec, target in zip(res, recs, y[:4], strict=True):
        assert rec["runs"] == 3 and rec["known_starts"] == 5   # the three candidates only: stored rows are free
        stored = score(train_y, np.tile(target, (len(train_y), 1)))
        sims = [c.r_actual for c in r.candidates if c.r_actual is not None and c.source != "training row"]
        assert rec["start_r_actual"] == pytest.approx(max(np.nanmax(stored), *sims), abs=1e-12)
        if r.best.source == "training row":   # answered by a stored row: its real features, never re-run
            j = int(np.argmax(stored))
            assert np.array_equal(r.best.theta, train_theta[j]) and np.allclose(r.best.actual, train_y[j])
    assert any(r.best.source == "training row" for r in res)
    none = refine(inv, inv.invert_many(y[:4], top_k=3), 3, popsize=4, strategy="corrected", known_starts=0)
    assert all(rec["known_starts"] == 0 for rec in none)
    assert np.mean([rec["start_r_actual"] for rec in none]) < np.mean([rec["start_r_actual"] for rec in recs])


def _biased(inv, monkeypatch) -> None:
    """The toy surrogate plus a smooth error of ~half a feature scale (the error a refine must learn)."""
    sur = inv.bundle.surrogate
    plain = type(sur).predict

    def predict(theta):
        theta = np.atleast_2d(theta)
        return plain(sur, theta) + 0.5 * inv.bundle.scales * np.sin(6.0 * theta.sum(1, keepdims=True))

    monkeypatch.setattr(sur, "predict", predict)


def test_with_a_biased_surrogate_the_correction_beats_cma_and_the_uncorrected_search(inv, monkeypatch) -> None:
    _, y = inv.bundle.data("test")
    start = inv.invert_many(y[:16], top_k=3)
    _biased(inv, monkeypatch)

    def mean_r(**kw) -> float:
        recs = refine(inv, copy.deepcopy(start), 32, popsize=4, known_starts=8, **kw)
        return float(np.mean([rec["r_actual"] or 0.0 for rec in recs]))

    corrected = mean_r(strategy="corrected")
    plain = mean_r(strategy="corrected", strategy_options={"correct": False})
    cma = mean_r(strategy="cma")
    assert corrected > plain + 0.01 and corrected > cma + 0.01, (corrected, plain, cma)


def test_a_corrected_refine_replays_from_its_log(inv, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    log = tmp_path / "refine.npz"
    first, _ = _run(inv, y[:3], log=log)
    again, recs2 = _run(inv, y[:3], log=log)
    assert _key(again) == _key(first)
    assert all(r["replayed_runs"] == r["runs"] == 12 for r in recs2) and recs2[0]["call"]["replayed_runs"] == 36
    cma = refine(inv, inv.invert_many(y[:3], top_k=3), 12, popsize=4, log=log, strategy="cma")  # no replay
    assert sum(r["replayed_runs"] for r in cma) <= 9


def test_a_refined_answer_below_one_half_is_flagged(inv) -> None:
    _, y = inv.bundle.data("test")
    far = y[:2] + 40.0 * inv.bundle.scales   # nothing the oscillator makes
    res, recs = _run(inv, far, budget=4)
    for r, rec in zip(res, recs, strict=True):
        assert rec["r_actual"] is not None and rec["r_actual"] < 0.5
        assert rec["warning"] and rec["warning"] in r.warnings and "below 0.5" in rec["warning"]
    _, ok = _run(inv, y[:2], budget=4)
    assert all(rec["r_actual"] >= 0.5 and rec["warning"] is None for rec in ok)


def test_bad_strategy_settings_are_one_clear_error(inv, bundle) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    _, y = inv.bundle.data("test")
    res = inv.invert_many(y[:1])
    with pytest.raises(InvphysError, match="unknown refine strategy 'bo'"):
        refine(inv, res, 4, strategy="bo")
    with pytest.raises(InvphysError, match="unknown corrected-refine option"):
        refine(inv, res, 4, strategy="corrected", strategy_options={"radius": 0.1})
    with pytest.raises(InvphysError, match="out of range"):
        refine(inv, res, 4, strategy="corrected", strategy_options={"radius0": 2.0})
    with pytest.raises(InvphysError, match="takes no options"):
        refine(inv, res, 4, strategy="cma", strategy_options={"radius0": 0.1})
    feats = [a for n, v in zip(inv.feature_names, y[0], strict=True) for a in ("--feature", f"{n}={v}")]
    out = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "4", "--sim-refine-strategy", "bo"])
    assert out.exit_code == 2 and "--sim-refine-strategy must be one of corrected, cma" in out.output
    out = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine-strategy", "corrected"])
    assert out.exit_code == 2 and "needs --sim-refine N" in out.output
    out = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "6", "--sim-refine-strategy",
                                   "corrected", "--json"])
    assert out.exit_code == 0, out.output


def test_a_batch_costs_evals_plus_second_evals_surrogate_rows_and_the_neighbours_are_the_nearest(inv, monkeypatch
                                                                                                  ) -> None:
    from invphys.evaluators.corrected_refine import CorrectedSettings, _nearest

    _, y = inv.bundle.data("test")
    start = inv.invert_many(y[:3], top_k=3)
    sur = inv.bundle.surrogate
    plain, rows = type(sur).predict, []
    monkeypatch.setattr(sur, "predict", lambda theta: (rows.append(len(np.atleast_2d(theta))), plain(sur, theta))[1])
    recs = refine(inv, start, 3 + 4 * 4, popsize=4, strategy="corrected", known_starts=8, stop=0)
    batches = sum((rec["runs"] - 3) // 4 for rec in recs)
    s = CorrectedSettings()
    stored = len(inv.bundle.data("train")[0])   # their residuals, once
    big = sum(n for n in rows if n >= 64) - stored   # the candidate searches (the runs' own: fewer rows a call)
    assert batches == 12 and big <= batches * (s.evals + s.second_evals), (big, batches)   # it was 2 x evals
    pts = np.random.default_rng(0).random((500, 3))
    pts[7] = pts[3]   # a tie: the lower index first, as a stable sort gives
    for k in (0, 1, 5, 16, 500, 600):
        c = pts[3] + 0.01
        assert _nearest(pts, c, k).tolist() == np.argsort(((pts - c) ** 2).sum(1), kind="stable")[:k].tolist()


def test_the_corrected_proposals_run_on_the_inverters_blas_threads(inv, monkeypatch) -> None:
    from threadpoolctl import threadpool_info

    _, y = inv.bundle.data("test")
    start = inv.invert_many(y[:1], top_k=3)
    sur = inv.bundle.surrogate
    plain, seen = type(sur).predict, []

    def predict(theta):
        seen.append({p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"})
        return plain(sur, theta)

    monkeypatch.setattr(sur, "predict", predict)
    inv.threads = 1
    refine(inv, start, 3 + 4, popsize=4, strategy="corrected", stop=0)
    assert seen[-1] == {1}   # the last calls: a batch's candidate search
