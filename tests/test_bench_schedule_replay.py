"""``benchmarks/bench_schedule_replay.py`` replays continuous batching on the host: its chunk rule must be the
engine's (same chunks, same slot-substeps as a real stream on the CPU), and its pricing what it says."""

from __future__ import annotations

import numpy as np
import pytest
from benchmark_modules import load

replay_mod = load("bench_schedule_replay")
LINEAR = (np.array([0.0, 2.0]), np.array([0.2, 2.2]))   # 0.2 ms with no run active, +1 ms per active run


def test_a_short_frame_idles_its_slot_to_the_chunk_end_and_rollover_does_not():
    nsub = np.array([10, 4, 6])   # queue order, one frame each, two slots
    got = replay_mod.replay(nsub, 1, 2, "chunked:16", LINEAR, host_ms=3.0)
    # chunk 1: runs 0 and 1 for 10 substeps (run 1's slot idles after 4); chunk 2: run 2 alone for 6
    assert got["chunks"] == 2 and got["slot_efficiency"] == pytest.approx(20 / 32)
    assert got["predicted_s"] == pytest.approx((4 * 2.2 + 6 * 1.2 + 6 * 1.2 + 2 * 3.0) / 1e3)
    # frames that roll over: run 2 takes run 1's slot after 4 substeps, and no slot idles
    roll = replay_mod.replay(nsub, 1, 2, "rollover:256", LINEAR, host_ms=3.0)
    assert roll["chunks"] == 2 and roll["slot_efficiency"] == pytest.approx(1.0)
    assert roll["predicted_s"] == pytest.approx((10 * 2.2 + 2 * 3.0) / 1e3)
    with pytest.raises(SystemExit, match="unknown policy"):
        replay_mod.replay(nsub, 1, 2, "chunked:0", LINEAR, host_ms=3.0)


def test_the_replay_chunks_a_stream_as_the_engine_does():
    pytest.importorskip("taichi")
    from anisompm_scene import build_scene
    from invphys_anisompm import Engine
    from invphys_anisompm.engine import frame_plan, run_dt_bound
    from invphys_anisompm.streaming import queue_order

    scene = build_scene(settle_seconds=0.04)
    model = scene.model(5).set_material("paste", E=[3e4, 2e5, 6e4, 9e5, 1e5], eta=[0.02, 0.05, 0.01, 0.03, 0.02])
    frames = 4
    engine = Engine(scene, backend="taichi", arch="cpu")
    out = dict(engine.stream(model, frames=frames, record_every=2, batch_size=2, min_chunk=100))
    assert all(r.guard_frames == 0 and r.failure is None for r in out.values()), "the replay assumes planned frames"
    nsub, _ = frame_plan(scene.options.fps, run_dt_bound(model, frames))
    assert len(set(nsub.tolist())) > 2, "runs must differ in cost for the test to mean anything"
    order = queue_order(engine.estimate_cost(model, frames), "longest_first")
    n_frames = frames + round(scene.options.settle_seconds * scene.options.fps)
    got = replay_mod.replay(nsub[order], n_frames, 2, "chunked:100", LINEAR, host_ms=0.0)
    c = engine.counters
    # a chunk longer than some frames (89-208 substeps here), so that slots idle and chunks differ by rule
    assert c.useful < c.launched
    assert replay_mod.replay(nsub[order], n_frames, 2, "chunked:1", LINEAR, host_ms=0.0)["chunks"] != c.chunks
    assert got["chunks"] == c.chunks
    assert got["slot_efficiency"] == pytest.approx(c.useful / c.launched)
