"""benchmarks/bench_pool_speed.py on the paper bundle (a private copy): the batched answer timed by stage, and
the stages restored afterwards."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from benchmark_modules import load
from test_inverter_support import paper_bundle

bench = load("bench_pool_speed")
FRESH = Path(__file__).resolve().parents[1] / "datasets" / "orange_peel_paper_fresh_uniform"


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return paper_bundle(tmp_path_factory.getbasetemp())


def test_stages_add_up_to_the_answer_time(bundle, tmp_path) -> None:
    from invphys.inverter import draws, pool

    before = (draws.sample_posterior, pool.nearest_rows, pool.PoolAnswers.__dict__["score"])
    out = tmp_path / "speed.json"
    assert bench.main(["--bundle", str(bundle), "--targets", f"uniform={FRESH}",
                       "--methods", "pool", "default", "--limit", "3", "--repeat", "1", "--draws", "64",
                       "--workers", "2", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["device"].startswith("cpu") and data["targets"] == {"uniform": 3}
    assert set(data["methods"]) == {"pool", "npe_best64"}
    for method, stages in (("pool", {"draws npe_best64", "neighbour search", "surrogate scoring", "moves",
                                     "uncertainty", "result objects"}), ("npe_best64", {"draws npe_best64"})):
        got = data["methods"][method]["uniform"]
        assert stages <= set(got["stages_ms_per_target"])
        assert sum(got["stages_ms_per_target"].values()) == pytest.approx(got["ms_per_target"], rel=1e-2, abs=0.01)
    for method in ("pool", "npe_best64"):   # all targets answered by 2 worker processes, first and later calls
        (w,) = data["methods"][method]["workers"]
        assert w["workers"] == 2 and w["targets"] == 3
        assert w["first_call_ms_per_target"] > 0 and w["later_calls_ms_per_target"] > 0
    assert (draws.sample_posterior, pool.nearest_rows, pool.PoolAnswers.__dict__["score"]) == before
