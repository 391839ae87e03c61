"""The refine's cost budget (``refine(cost_budget=)``, ``invert --sim-refine-cost``) on the toy.

Real components: the toy bundle, its oscillator simulator (with a run-cost estimate added: the toy's own
gives none) and the refine stream. A capped target's runs must be the first runs of the same refine without
the budget, cut exactly where the estimated costs (known from the parameters alone) exceed it, whatever the
batch size, ask workers or target order.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from benchmark_modules import load
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)

from invphys.core.errors import InvphysError
from invphys.inverter.refine import COST_REFERENCE_ROWS, COST_REFERENCE_SEED, refine, run_cost

BUDGET, POP = 20, 4


class CostedToy:
    """The toy bundle's simulator with a cost estimate that grows steeply with the first parameter."""

    def __init__(self, sim) -> None:
        self.sim = sim

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def estimate_cost(self, params: np.ndarray) -> np.ndarray:
        u = self.sim.parameter_space().normalize(np.atleast_2d(params))
        return 1.0 + 9.0 * u[:, 0] ** 2


def _run(inv, y, cost_budget=None, **kw):
    res = inv.invert_many(y, top_k=3)
    recs = refine(inv, res, BUDGET, popsize=POP, strategy="corrected", known_starts=0, stop=0.0,
                  simulator=CostedToy(inv.simulator()), cost_budget=cost_budget, **kw)
    return res, recs


def _thetas(log: Path) -> np.ndarray:
    """A one-target refine log's simulated points in run order."""
    z = np.load(log)
    assert len(set(z["tid"].tolist())) == 1
    return z["theta"][np.argsort(z["seq"])]


def test_a_typical_run_costs_one_on_average_over_the_box(inv) -> None:
    sim = CostedToy(inv.simulator())
    space = sim.parameter_space()
    ref = np.random.default_rng(COST_REFERENCE_SEED).random((COST_REFERENCE_ROWS, space.dim))
    cost = run_cost(sim, 10)
    assert cost.budget == 10.0 and np.mean(cost.of(ref)) == pytest.approx(1.0)
    assert cost.of(np.array([[1.0] * space.dim]))[0] == pytest.approx(10.0 / np.mean(1 + 9 * ref[:, 0] ** 2))


def test_a_capped_target_stops_where_its_costs_say_and_its_runs_are_a_prefix(inv, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    y = y[:6]
    full_res, full, thetas = [], [], []
    for k, row in enumerate(y):   # one target per refine, so its log holds its runs alone
        r, rec = _run(inv, row[None, :], log=tmp_path / f"{k}.npz")
        full_res += r
        full += rec
        thetas.append(_thetas(tmp_path / f"{k}.npz"))
    assert all(rec["runs"] == BUDGET and not rec["capped"] and rec["settings"]["cost_budget"] is None
               for rec in full)
    of = run_cost(CostedToy(inv.simulator()), 1.0).of
    for rec, th in zip(full, thetas, strict=True):   # without a cap the costs are recorded all the same
        assert rec["cost_by_run"] == pytest.approx(of(th).tolist(), rel=1e-12)
        assert rec["cost"] == pytest.approx(sum(rec["cost_by_run"]), rel=1e-12)
    costs = sorted(float(np.sum(of(th))) for th in thetas)
    assert costs[0] > 0 and costs[0] < costs[-1]
    cap = float(np.median(costs))   # about half the targets are cut
    res, recs = _run(inv, y, cost_budget=cap, batch_size=1, ask_workers=0)
    for r, rec, ref, th in zip(res, recs, full, thetas, strict=True):
        assert len(th) == BUDGET
        n = int(np.sum(np.cumsum(of(th)) <= cap * (1 + 1e-12)))
        assert rec["runs"] == min(n, BUDGET) and rec["capped"] == (n < BUDGET)
        assert rec["best_r_by_run"] == ref["best_r_by_run"][:rec["runs"]]   # the same runs, cut short
        assert rec["cost"] <= cap * (1 + 1e-12) and sum(rec["batches"]) == rec["runs"]
        assert r.best.r_actual == rec["r_actual"] == max(ref["best_r_by_run"][:rec["runs"]])
        assert rec["settings"]["cost_budget"] == cap and rec["cost_by_run"] == ref["cost_by_run"][:rec["runs"]]
    assert 0 < sum(rec["capped"] for rec in recs) < len(recs)
    # the replay benchmark, on the uncapped refine's records (their cost_by_run), gives the capped refine
    rp = load("bench_refine_replay")
    assert [rp.replay(ref, ref["batches"], None, 0, 0.0, cap)[:2] for ref in full] == \
        [(rec["runs"], rec["r_actual"]) for rec in recs]
    assert {rp.replay(ref, ref["batches"], None, 0, 0.0, cap)[2] for ref in full} == {"capped", "ran"}
    assert recs[0]["call"]["capped"] == sum(rec["capped"] for rec in recs)
    key = [(tuple(r.best.theta), rec["runs"], rec["cost"]) for r, rec in zip(res, recs, strict=True)]
    for batch, workers in ((3, 2), (7, 0)):
        r2, rec2 = _run(inv, y, cost_budget=cap, batch_size=batch, ask_workers=workers)
        assert [(tuple(r.best.theta), rec["runs"], rec["cost"]) for r, rec in zip(r2, rec2, strict=True)] == key
    r3, rec3 = _run(inv, y[::-1], cost_budget=cap, batch_size=3, ask_workers=2)
    assert [(tuple(r.best.theta), rec["runs"], rec["cost"]) for r, rec in zip(r3, rec3, strict=True)][::-1] == key


def test_bad_budgets_and_a_simulator_without_costs_are_one_error(inv) -> None:
    _, y = inv.bundle.data("test")
    for bad in (0, -1.0, float("nan"), "x", True):
        with pytest.raises(InvphysError, match="refine cost budget must be a number of typical runs"):
            refine(inv, inv.invert_many(y[:1]), 4, simulator=CostedToy(inv.simulator()), cost_budget=bad)
    with pytest.raises(InvphysError, match="estimates no run cost"):
        refine(inv, inv.invert_many(y[:1]), 4, cost_budget=8)


def test_the_default_cost_budget_is_the_run_budget_where_the_simulator_estimates_costs(inv) -> None:
    _, y = inv.bundle.data("test")
    y = y[:12]
    res, recs = _run(inv, y, cost_budget="budget")
    res_b, recs_b = _run(inv, y, cost_budget=float(BUDGET))
    assert [rec["runs"] for rec in recs] == [rec["runs"] for rec in recs_b] and any(rec["capped"] for rec in recs)
    assert [tuple(r.best.theta) for r in res] == [tuple(r.best.theta) for r in res_b]
    assert [rec["settings"]["cost_budget"] for rec in recs] == [float(BUDGET)] * len(recs)
    # the toy's own simulator estimates no cost: "budget" is off there, an explicit budget is an error
    plain = refine(inv, inv.invert_many(y[:1], top_k=3), 6, popsize=POP, stop=0.0, cost_budget="budget")
    assert plain[0]["settings"]["cost_budget"] is None and not plain[0]["capped"] and plain[0]["runs"] == 6


def test_the_cli_option(inv, bundle) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    _, y = inv.bundle.data("test")
    feats = [a for n, v in zip(inv.feature_names, y[0], strict=True) for a in ("--feature", f"{n}={v}")]
    runner = CliRunner()
    for extra, msg in ((["--sim-refine", "8", "--sim-refine-cost", "-1"], "--sim-refine-cost must be a number"),
                       (["--sim-refine-cost", "8"], "--sim-refine-cost needs --sim-refine N"),
                       (["--sim-refine", "8", "--sim-refine-cost", "8"], "estimates no run cost")):
        out = runner.invoke(app, ["invert", str(bundle), *feats, *extra])
        assert out.exit_code == 2 and msg in out.output and "Traceback" not in out.output, out.output
    for extra in ([], ["--sim-refine-cost", "0"]):   # the toy estimates no cost: the default and 0 are off
        out = runner.invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "8", "--sim-refine-popsize", "4",
                                  "--sim-refine-stop", "0", "--json", *extra])
        assert out.exit_code == 0, out.output
        rec = json.loads(out.stdout)["results"][0]["sim_refine"]
        assert rec["runs"] == 8 and not rec["capped"] and rec["settings"]["cost_budget"] is None
        assert rec["cost"] == 0.0 and rec["cost_by_run"] == []   # the toy estimates no run cost


def test_a_capped_refines_log_replays_into_one_without_the_cap(inv, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    y = y[:6]
    log = tmp_path / "refine.npz"
    _, capped = _run(inv, y, cost_budget=8.0, log=log)
    assert any(rec["capped"] for rec in capped)
    res, recs = _run(inv, y, log=log)   # no cap: the capped runs replay, the rest are simulated
    fresh_res, fresh = _run(inv, y)
    assert recs[0]["call"]["replayed_runs"] == sum(rec["runs"] for rec in capped)
    assert [rec["best_r_by_run"] for rec in recs] == [rec["best_r_by_run"] for rec in fresh]
    assert [tuple(r.best.theta) for r in res] == [tuple(r.best.theta) for r in fresh_res]


def test_a_broken_cost_estimate_is_one_error(inv) -> None:
    _, y = inv.bundle.data("test")

    class Broken(CostedToy):
        def estimate_cost(self, params):
            c = super().estimate_cost(params)
            return c if len(c) == 256 else np.full(len(c) + self.extra, np.nan)   # the reference sample passes

    for extra, msg in ((0, "estimate_cost gave a negative or non-finite run cost"),
                       (1, "estimate_cost gave 4 costs for 3 rows")):
        sim = Broken(inv.simulator())
        sim.extra = extra
        with pytest.raises(InvphysError, match=msg):
            refine(inv, inv.invert_many(y[:1], top_k=3), 4, popsize=POP, simulator=sim, cost_budget=8)
