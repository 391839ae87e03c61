"""The refine's tells and asks in background threads (``refine(ask_workers=N)``): the same answers, runs and
log as asking in the stream's own loop, whatever the number of workers, batch size, strategy or completion
order; a log written with workers replays without a run; the record says how long the stream waited."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from test_inverter_refine import ShuffledToy, _answers, _key
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)

from invphys.core.errors import InvphysError


def _points(recs) -> list:
    return [(r["runs"], r["stopped"], r["best_r_by_run"]) for r in recs]


@pytest.mark.parametrize("strategy", ["cma", "corrected"])
def test_answers_with_ask_workers_equal_the_serial_ones(inv, strategy) -> None:
    ref, recs = _answers(inv, batch_size=4, ask_workers=0, strategy=strategy)
    assert recs[0]["call"]["ask_workers"] == 0
    for workers, bs, seed in ((1, 4, None), (3, 1, None), (2, 16, 1), (3, 4, 2)):
        sim = None
        if seed is not None:
            sim = ShuffledToy(inv.simulator().config)
            sim.order_seed = seed
        got, recs2 = _answers(inv, batch_size=bs, ask_workers=workers, strategy=strategy, simulator=sim)
        assert _key(got) == _key(ref)
        assert _points(recs2) == _points(recs)
        assert recs2[0]["call"]["ask_workers"] == workers and recs2[0]["call"]["ask_wait_s"] >= 0.0
        assert all(r["ask_cpu_s"] <= r["ask_s"] + 0.05 for r in recs2)


def test_a_log_written_with_ask_workers_replays_without_runs(inv, tmp_path) -> None:
    log = tmp_path / "refine.npz"
    ref, recs = _answers(inv, batch_size=4, ask_workers=2, log=log)
    again, recs2 = _answers(inv, batch_size=4, ask_workers=0, log=log)
    assert _key(again) == _key(ref)
    assert recs2[0]["call"]["replayed_runs"] == recs2[0]["call"]["runs"] == recs[0]["call"]["runs"]


def test_a_slow_ask_does_not_hold_other_targets_rows(inv) -> None:
    """While one target's ask is slow, the stream feeds the other targets' rows (it waits only with nothing
    in flight); the serial loop holds every target for it. The answers stay the same."""
    from invphys.evaluators import corrected_refine

    slow, seen, lock = corrected_refine.CorrectedSearch.ask, set(), threading.Lock()

    def ask(self, left):   # every target's first search ask is slow: five of them, while the others have rows
        with lock:
            first = self.t.tid not in seen
            seen.add(self.t.tid)
        if first:
            time.sleep(0.05)
        return slow(self, left)

    corrected_refine.CorrectedSearch.ask = ask
    try:
        ref, recs = _answers(inv, batch_size=4, ask_workers=0, simulator=_slots(inv, 8))
        seen.clear()
        got, recs2 = _answers(inv, batch_size=4, ask_workers=2, simulator=_slots(inv, 8))
    finally:
        corrected_refine.CorrectedSearch.ask = slow
    assert _key(got) == _key(ref)
    serial, background = recs[0]["call"], recs2[0]["call"]
    assert serial["ask_wait_s"] == pytest.approx(serial["ask_s"]) and serial["ask_wait_s"] >= 5 * 0.05
    assert background["ask_wait_s"] < 0.8 * serial["ask_wait_s"]   # measured about half


def _slots(inv, n):
    sim = ShuffledToy(inv.simulator().config)
    sim.slots = n
    return sim


def test_bad_ask_workers_are_one_error(inv) -> None:
    with pytest.raises(InvphysError, match="ask workers"):
        _answers(inv, n=1, ask_workers=-1)
    assert np.isfinite(_answers(inv, n=1, ask_workers=1)[1][0]["ask_s"])
