"""The simulator refine with its features extracted in worker processes (``refine(extract_workers=N)``,
``invert --sim-refine-workers N``): the same answers as extracting in the refining process, whatever the
completion order, and the stream is reopened when it runs dry while features are still being extracted."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_inverter_refine import ShuffledToy, _answers, _key
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)

from invphys.core.errors import InvphysError
from invphys.evaluators.stream_refine import feed_features

TESTS = Path(__file__).resolve().parent


def test_answers_with_extraction_workers_equal_those_without(inv) -> None:
    ref, recs = _answers(inv, batch_size=4)
    got, recs2 = _answers(inv, batch_size=4, extract_workers=2)
    assert _key(got) == _key(ref)
    assert [r["runs"] for r in recs2] == [r["runs"] for r in recs] == [16] * 5
    shuffled = ShuffledToy(inv.simulator().config)
    shuffled.order_seed = 3
    assert _key(_answers(inv, batch_size=4, simulator=shuffled, extract_workers=2)[0]) == _key(ref)
    with pytest.raises(InvphysError, match="extract workers"):
        _answers(inv, n=1, extract_workers=-1)


def test_a_stream_that_runs_dry_while_features_are_pending_is_reopened(inv) -> None:
    """Feed 3 rows, and 2 more only once the first 3 came back: with a pool the first stream ends with
    their features still pending, so the next rows need a second stream; every row is yielded once."""
    from invphys.plugins.executors._extract_pool import ExtractionPool

    sim = inv.simulator()
    ext = inv.extractor(sim)
    rows = np.asarray(inv.bundle.data("test")[0][:5], dtype=np.float64)  # normalised parameters that simulate
    opened = []
    inner = sim.simulate_feed

    def counted(feeder, batch_size=None):
        opened.append(1)
        yield from inner(feeder, batch_size)

    sim.simulate_feed = counted
    with ExtractionPool(ext, 2) as pool:
        run = feed_features(sim, ext, 4, pool)
        queue, seen = [rows[:3]], []

        def feeder(free: int):
            return queue.pop(0) if queue else None

        for i, y, _s, _d in run(feeder):
            seen.append(i)
            assert np.all(np.isfinite(y))
            if len(seen) == 3:
                queue.append(rows[3:])
    assert sorted(seen) == [0, 1, 2, 3, 4] and len(opened) >= 2  # rows 3, 4 came through a reopened stream
    plain = [y for _i, y, _s, _d in feed_features(sim, ext, 4)(lambda free, q=[rows]: q.pop() if q else None)]
    assert len(plain) == 5


def test_the_cli_option_is_checked_and_used(bundle, tmp_path) -> None:
    import invphys

    y = invphys.load_inverter(bundle).bundle.data("test")[1][:2]
    names = invphys.load_inverter(bundle).feature_names
    target = tmp_path / "t.csv"
    target.write_text(",".join(names) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in y) + "\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    base = [sys.executable, "-m", "invphys.cli", "invert", str(bundle), "--target", str(target), "--json"]
    bad = subprocess.run([*base, "--sim-refine-workers", "2"], capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and "needs --sim-refine" in bad.stderr
    outs = []
    for workers in ("0", "2"):
        ok = subprocess.run([*base, "--sim-refine", "8", "--sim-refine-popsize", "4", "--sim-refine-workers", workers],
                            capture_output=True, text=True, env=env)
        assert ok.returncode == 0, ok.stderr
        outs.append([(r["candidates"][0]["theta"], r["candidates"][0]["r_actual"])
                     for r in json.loads(ok.stdout)["results"]])
    assert outs[0] == outs[1]
