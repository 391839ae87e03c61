"""The refine's stall stop (``refine(patience=, min_gain=)``, ``invert --sim-refine-patience/-min-gain``) on the toy.

Real components: the toy bundle, its oscillator simulator and the refine stream. A stalled target's runs must
be the first runs of the same refine without the rule, whatever the batch size, ask workers or target order,
and it must stop exactly where the rule, replayed on the unstopped refine's per-run bests and told
generations, says.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from benchmark_modules import load
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)

from invphys.core.errors import InvphysError
from invphys.inverter.refine import refine

BUDGET, POP, PATIENCE = 20, 4, 4


def _run(inv, y, **kw):
    res = inv.invert_many(y, top_k=3)
    recs = refine(inv, res, BUDGET, popsize=POP, strategy="corrected", known_starts=0, stop=0.0, **kw)
    return res, recs


def _key(res, recs) -> list[tuple]:
    return [(tuple(r.best.theta), r.best.r_actual, rec["runs"], rec["stalled"], tuple(rec["batches"]))
            for r, rec in zip(res, recs, strict=True)]


def _expected_runs(best: list[float], batches: list[int], gain: float) -> int:
    """Where the rule stops a target, from the unstopped refine's record (no free starts: best(0) is -inf)."""
    bests, n = [-np.inf, *best], 0
    for size in batches:
        if n >= batches[0] and n >= PATIENCE:   # after the starts, n >= patience: best(n) - best(n - P) < gain
            now, before = bests[n], bests[n - PATIENCE]
            if (0.0 if now == before else now - before) < gain:
                return n
        n += size
    return n


def test_a_stalled_target_stops_where_the_rule_says_and_its_runs_are_a_prefix(inv) -> None:
    _, y = inv.bundle.data("test")
    y = y[:6]
    full_res, full = _run(inv, y)
    assert all(rec["runs"] == BUDGET and not rec["stalled"] and sum(rec["batches"]) == BUDGET for rec in full)
    assert all(rec["batches"] == [3, 4, 4, 4, 4, 1] for rec in full)   # 3 starts, then POP per generation
    gains = sorted(rec["best_r_by_run"][6] - rec["best_r_by_run"][2] for rec in full)  # at 7 runs, over runs 4-7
    gain = float(np.mean(gains[2:4]))   # some targets stall at 7 runs, others later
    expected = [_expected_runs(rec["best_r_by_run"], rec["batches"], gain) for rec in full]
    assert len(set(expected)) > 1 and min(expected) == 7 and max(expected) > 7   # at several decision points
    res, recs = _run(inv, y, patience=PATIENCE, min_gain=gain, batch_size=1, ask_workers=0)
    assert [rec["runs"] for rec in recs] == expected
    for rec, ref, r in zip(recs, full, res, strict=True):
        assert rec["best_r_by_run"] == ref["best_r_by_run"][:rec["runs"]]   # the same runs, cut short
        assert rec["batches"] == ref["batches"][:len(rec["batches"])] and sum(rec["batches"]) == rec["runs"]
        assert rec["stalled"] == (rec["runs"] < BUDGET) and not rec["stopped"]
        assert r.best.r_actual == rec["r_actual"] == max(ref["best_r_by_run"][:rec["runs"]])
        assert rec["settings"]["patience"] == PATIENCE and rec["settings"]["min_gain"] == gain
    # the replay benchmark, on the unstopped refine's records, gives the stalled refine's runs and answers
    rp = load("bench_refine_replay")
    assert [rp.replay(ref, ref["batches"], None, PATIENCE, gain)[:2] for ref in full] == \
        [(rec["runs"], rec["r_actual"]) for rec in recs]
    ref_key = _key(res, recs)
    assert recs[0]["call"]["stalled"] == sum(rec["stalled"] for rec in recs)
    for batch, workers in ((3, 2), (7, 0), (7, 2)):
        assert _key(*_run(inv, y, patience=PATIENCE, min_gain=gain, batch_size=batch, ask_workers=workers)) == ref_key
    back = _run(inv, y[::-1], patience=PATIENCE, min_gain=gain, batch_size=3, ask_workers=2)
    assert _key(*back)[::-1] == ref_key
    # off: patience 0 or None is the unstopped refine
    assert _key(*_run(inv, y[:2], patience=None)) == _key(full_res[:2], full[:2])


def test_the_cli_options_and_bad_values_are_one_error(inv, bundle) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    _, y = inv.bundle.data("test")
    for kw, msg in (({"patience": -1}, "refine patience must be a whole number"),
                    ({"patience": 2.5}, "refine patience must be a whole number"),
                    ({"patience": True}, "refine patience must be a whole number"),
                    ({"patience": 4, "min_gain": -0.1}, "refine min gain must be an R_actual gain in"),
                    ({"patience": 4, "min_gain": float("nan")}, "refine min gain must be an R_actual gain in"),
                    ({"patience": 4, "min_gain": "x"}, "refine min gain must be an R_actual gain in")):
        with pytest.raises(InvphysError, match=msg):
            refine(inv, inv.invert_many(y[:1]), 4, **kw)
    feats = [a for n, v in zip(inv.feature_names, y[0], strict=True) for a in ("--feature", f"{n}={v}")]
    runner = CliRunner()
    for extra, msg in ((["--sim-refine", "12", "--sim-refine-patience", "0"], "--sim-refine-patience must be in 1"),
                       (["--sim-refine", "12", "--sim-refine-patience", "4", "--sim-refine-min-gain", "1.5"],
                        "--sim-refine-min-gain must be an R_actual gain in [0, 1]"),
                       (["--sim-refine", "12", "--sim-refine-min-gain", "0.1"],
                        "--sim-refine-min-gain needs --sim-refine-patience"),
                       (["--sim-refine-patience", "4"], "--sim-refine-patience needs --sim-refine N")):
        out = runner.invoke(app, ["invert", str(bundle), *feats, *extra])
        assert out.exit_code == 2 and msg in out.output and "Traceback" not in out.output, out.output
    out = runner.invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "16", "--sim-refine-popsize", "4",
                              "--sim-refine-stop", "0", "--sim-refine-patience", "4", "--sim-refine-min-gain", "1",
                              "--json"])
    assert out.exit_code == 0, out.output
    rec = json.loads(out.stdout)["results"][0]["sim_refine"]
    # gain 1 is never reached: with 8 stored rows as free starts (best(0) known), the 4 starts' runs are enough
    assert rec["stalled"] and rec["runs"] == 4 and rec["batches"] == [4] and rec["known_starts"] == 8
    assert rec["settings"]["patience"] == 4 and rec["settings"]["min_gain"] == 1.0
    out = runner.invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "16", "--sim-refine-popsize", "4",
                              "--sim-refine-patience", "4", "--sim-refine-min-gain", "1"])
    assert out.exit_code == 0 and "(4 simulator runs" in out.output and "stopped: stalled" in out.output, out.output
    out = runner.invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "8", "--sim-refine-popsize", "4",
                              "--sim-refine-patience", "4", "--json"])
    assert out.exit_code == 0, out.output
    assert json.loads(out.stdout)["results"][0]["sim_refine"]["settings"]["min_gain"] == 0.01
