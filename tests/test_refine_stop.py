"""The refine's stop at the noise floor (``refine(stop=...)``, ``invert --sim-refine-stop``) on the toy.

Real components: the toy bundle, its oscillator simulator and the refine stream. A stopped target's runs
must be the first runs of the same refine without a stop, whatever the batch size, completion order or
other targets, and a log written with a stop replays into a refine without one.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_inverter_refine import ShuffledToy
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)

from invphys.core.errors import InvphysError
from invphys.inverter.refine import refine

BUDGET, POP = 20, 4


def _run(inv, y, **kw):
    res = inv.invert_many(y, top_k=3)
    recs = refine(inv, res, BUDGET, popsize=POP, strategy="corrected", known_starts=0, **kw)
    return res, recs


def _key(res, recs) -> list[tuple]:
    return [(tuple(r.best.theta), r.best.r_actual, rec["runs"], rec["stopped"]) for r, rec in zip(res, recs,
                                                                                                    strict=True)]


def test_a_target_stops_at_the_stop_score_and_its_runs_are_a_prefix_of_the_unstopped_ones(inv, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    y = y[:6]
    full_res, full = _run(inv, y, stop=0.0)
    assert all(rec["runs"] == BUDGET and not rec["stopped"] for rec in full)
    finals = sorted(rec["r_actual"] for rec in full)
    stop = float(np.mean(finals[2:4]))   # some targets reach it, some do not
    log = tmp_path / "refine.npz"
    res, recs = _run(inv, y, stop=stop, batch_size=1, log=log)
    assert 0 < sum(rec["stopped"] for rec in recs) < len(recs)
    for rec, ref, r, rf in zip(recs, full, res, full_res, strict=True):
        assert rec["best_r_by_run"] == ref["best_r_by_run"][:rec["runs"]]   # the same runs, cut short
        if rec["stopped"]:
            assert rec["runs"] < BUDGET and rec["r_actual"] >= stop and r.best.r_actual == rec["r_actual"]
            # decided at a generation's end: the generation before had not reached it (3 starts, then POP per batch)
            assert rec["runs"] == 3 or ref["best_r_by_run"][rec["runs"] - POP - 1] < stop
        else:
            assert rec["runs"] == BUDGET and _key([r], [rec])[0][:2] == _key([rf], [ref])[0][:2]
    ref_key = _key(res, recs)
    assert _key(*_run(inv, y, stop=stop, batch_size=7)) == ref_key
    back = _run(inv, y[::-1], stop=stop, batch_size=3)
    assert _key(*back)[::-1] == ref_key
    assert _key(*_run(inv, y[2:4], stop=stop)) == ref_key[2:4]
    shuffled = ShuffledToy(inv.simulator().config)
    shuffled.order_seed = 5
    assert _key(*_run(inv, y, stop=stop, batch_size=4, simulator=shuffled)) == ref_key
    # the stopped refine's log replays into the refine without a stop: its runs are replayed, the rest simulated
    again_res, again = _run(inv, y, stop=0.0, log=log)
    assert [rec["replayed_runs"] for rec in again] == [rec["runs"] for rec in recs]
    assert _key(again_res, again) == _key(full_res, full)


def test_the_record_counts_runs_and_bad_stops_are_one_error(inv, bundle) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    _, y = inv.bundle.data("test")
    _, recs = _run(inv, y[:2], stop=1.0)   # 1: never stops (as 0)
    assert all(rec["runs"] == BUDGET and not rec["stopped"] and rec["settings"]["stop"] == 1.0 for rec in recs)
    assert all(len(rec["best_r_by_run"]) == BUDGET and rec["best_r_by_run"][-1] == rec["r_actual"] for rec in recs)
    assert recs[0]["call"]["stopped"] == 0 and recs[0]["call"]["ask_s"] > 0
    for bad in (1.5, -0.1, "high", None, True):
        with pytest.raises(InvphysError, match="refine stop must be an R_actual in"):
            refine(inv, inv.invert_many(y[:1]), 4, stop=bad)
    feats = [a for n, v in zip(inv.feature_names, y[0], strict=True) for a in ("--feature", f"{n}={v}")]
    out = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "4", "--sim-refine-stop", "1.5"])
    assert out.exit_code == 2 and "--sim-refine-stop must be an R_actual in [0, 1]" in out.output
    out = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine-stop", "0.9"])
    assert out.exit_code == 2 and "--sim-refine-stop needs --sim-refine N" in out.output
    out = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "12", "--sim-refine-popsize", "4",
                                   "--sim-refine-stop", "0.01", "--json"])
    assert out.exit_code == 0, out.output
    import json

    rec = json.loads(out.stdout)["results"][0]["sim_refine"]
    assert rec["stopped"] and rec["runs"] < 12 and rec["settings"]["stop"] == 0.01
