"""The simulator refine through one open stream (``invphys.inverter.refine``, ``invert --sim-refine``) on the toy.

Answers must not depend on the batch size, on the order in which runs complete, or on which other targets
share the stream; a killed refine resumes from its log (a real subprocess) to the same answers.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_dataset_toy import ToyOscillator
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)

from invphys.core.errors import InvphysError
from invphys.inverter.refine import refine

TESTS = Path(__file__).resolve().parent


class ShuffledToy(ToyOscillator):
    """An open stream that keeps up to ``slots`` rows in flight and finishes them in a seeded random order
    (a new row may finish before older ones), feeding new rows whenever a slot is free."""

    slots = 5
    order_seed = 0

    def simulate_feed(self, feeder, batch_size=None):
        rng = np.random.default_rng(self.order_seed)
        waiting, flight, fed = [], [], 0
        while True:
            if len(flight) < self.slots:
                rows = feeder(self.slots - len(flight))
                if rows is not None and len(rows):
                    waiting += [(fed + j, r) for j, r in enumerate(np.atleast_2d(rows))]
                    fed += len(rows)
                while waiting and len(flight) < self.slots:
                    flight.append(waiting.pop(0))
            if not flight:
                return
            i, row = flight.pop(int(rng.integers(len(flight))))
            yield i, self.simulate(row[None, :])[0]


def _answers(inv, n=5, budget=16, **kw):
    _, y = inv.bundle.data("test")
    res = inv.invert_many(y[:n], top_k=3)
    recs = refine(inv, res, budget, popsize=4, **kw)
    return res, recs


def _key(res) -> list[tuple]:
    return [(tuple(r.best.theta), r.best.r_actual, r.best.source) for r in res]


def test_answers_do_not_depend_on_batch_size_or_completion_order(inv) -> None:
    ref, recs = _answers(inv, batch_size=1)
    for r, rec in zip(ref, recs, strict=True):
        assert rec["runs"] == 16 and r.best.r_actual == rec["r_actual"] >= rec["start_r_actual"]
        assert r.best.r_actual >= max(c.r_actual for c in r.candidates[1:] if c.r_actual is not None)
    assert sum(rec["improved"] for rec in recs) >= 2   # the search does find better points
    for bs in (4, 16):
        assert _key(_answers(inv, batch_size=bs)[0]) == _key(ref)
    sim = inv.simulator()
    for seed in (1, 2):
        shuffled = ShuffledToy(sim.config)
        shuffled.order_seed = seed
        assert _key(_answers(inv, batch_size=4, simulator=shuffled)[0]) == _key(ref)


def test_a_target_gets_its_answer_whatever_shares_its_stream(inv) -> None:
    _, y = inv.bundle.data("test")
    res = inv.invert_many(y[:5], top_k=3)
    refine(inv, res, 12, popsize=4)
    alone = inv.invert_many(y[3:4], top_k=3)
    refine(inv, alone, 12, popsize=4)
    rev = inv.invert_many(y[:5][::-1], top_k=3)
    refine(inv, rev, 12, popsize=4)
    assert _key(alone) == _key(res[3:4]) and _key(rev)[::-1] == _key(res)


def test_a_budget_below_the_starts_simulates_the_first_starts_only(inv) -> None:
    res, recs = _answers(inv, n=2, budget=2, known_starts=0)
    for r, rec in zip(res, recs, strict=True):
        assert rec["runs"] == 2 and not rec["improved"] and r.candidates[2].r_actual is None
    with pytest.raises(InvphysError, match="refine budget"):
        _answers(inv, n=1, budget=0)


def _cli(bundle: Path, target: Path, log: Path | None, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "invphys.cli", "invert", str(bundle), "--target", str(target), "--sim-refine", "12",
           "--sim-refine-popsize", "4", "--sim-batch", "2", "--json", *extra]
    if log is not None:
        cmd += ["--sim-refine-log", str(log)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def test_a_killed_refine_resumes_from_its_log(inv, bundle, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    target = tmp_path / "targets.csv"
    target.write_text(",".join(inv.feature_names) + "\n" + "\n".join(",".join(repr(float(v)) for v in row)
                                                                    for row in y[:3]) + "\n")
    slow = ("--sim-option", "sleep_s=0.15")
    log = tmp_path / "refine.npz"
    proc = _cli(bundle, target, log, *slow)
    deadline = time.time() + 120
    while not log.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert log.exists() and proc.returncode == -signal.SIGKILL, "the refine must be killed mid-way"
    with np.load(log) as z:
        logged = len(z["seq"])
    assert 0 < logged < 36
    resumed = _cli(bundle, target, log, *slow)
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    fresh = _cli(bundle, target, None)
    out2, err2 = fresh.communicate(timeout=300)
    assert fresh.returncode == 0, err2
    a, b = json.loads(out)["results"], json.loads(out2)["results"]
    assert [r["candidates"][0]["theta"] for r in a] == [r["candidates"][0]["theta"] for r in b]
    assert [r["sim_refine"]["r_actual"] for r in a] == [r["sim_refine"]["r_actual"] for r in b]
    call = a[0]["sim_refine"]["call"]
    assert call["runs"] == 36 and call["replayed_runs"] >= logged and f"runs replayed from {log}" in err
    with np.load(log) as z:
        assert len(z["seq"]) == 36


def test_refine_log_refuses_a_foreign_file_and_options_need_sim_refine(inv, bundle, tmp_path) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    _, y = inv.bundle.data("test")
    feats = [a for n, v in zip(inv.feature_names, y[0], strict=True) for a in ("--feature", f"{n}={v}")]
    mine = tmp_path / "mine.npz"
    mine.write_bytes(b"not a log")
    res = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "4", "--sim-refine-log", str(mine)])
    assert res.exit_code == 2 and "not a refine log" in res.output and mine.read_bytes() == b"not a log"
    res = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine-popsize", "4"])
    assert res.exit_code == 2 and "needs --sim-refine N" in res.output
    res = CliRunner().invoke(app, ["invert", str(bundle), *feats, "--sim-refine", "0"])
    assert res.exit_code == 2 and "--sim-refine must be in 1 .. 100000" in res.output
