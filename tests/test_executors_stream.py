"""The optional streaming hook: ``Simulator.simulate_stream`` (default and the cheese-cut override) and
the local executor handing a ``native_stream`` simulator all its rows in one continuous-batching stream."""

from __future__ import annotations

import numpy as np
import pytest
from test_dataset_toy import ToyOscillator

from invphys.core.dataset import config_hash
from invphys.plugins.executors import LocalExecutor
from invphys.plugins.executors._batch import build_plugins


def test_default_stream_falls_back_to_the_batch_api() -> None:
    sim = ToyOscillator()
    space = sim.parameter_space()
    params = space.denormalize(np.random.default_rng(0).random((5, space.dim)))
    assert not sim.native_stream
    got = list(sim.simulate_stream(params, batch_size=2))
    assert [i for i, _ in got] == [0, 1, 2, 3, 4]
    for (_, res), ref in zip(got, sim.simulate(params), strict=True):
        np.testing.assert_array_equal(res.params, ref.params)
        assert (res.ok, res.failure) == (ref.ok, ref.failure)
        for a, b in zip(res.trajectory.positions if res.ok else [], ref.trajectory.positions if ref.ok else [],
                        strict=True):
            np.testing.assert_array_equal(a, b)


def test_local_executor_streams_a_continuous_cheese_simulator() -> None:
    pytest.importorskip("taichi")
    from invphys_cheese_cut.parameters import parameter_space

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(1).random((5, space.dim)))
    base = {"type": "cheese_cut", "preset": "tiny", "arch": "cpu", "batch_size": 2}
    feats = {"type": "cheese_cut_features"}
    out = {}
    # the warm simulator the executor will use (cached per process: other tests may have used it before)
    sim, _ = build_plugins({**base, "scheduling": "continuous"}, feats)
    useful_before = sim.engine.counters.useful
    for scheduling in ("lockstep", "continuous"):
        spec = {**base, "scheduling": scheduling}
        rows = list(LocalExecutor().run(spec, feats, params, batch_size=2))
        assert sorted(i for i, _ in rows) == list(range(5))
        out[scheduling] = dict(rows)
    assert sim.native_stream
    # one stream over all five rows on that warm simulator: its useful slot-substeps are exactly the runs'
    assert sim.engine.counters.useful - useful_before == sum(out["continuous"][i].stats.substeps for i in range(5))
    for i in range(5):
        a, b = out["continuous"][i], out["lockstep"][i]
        assert a.ok == b.ok and a.failure == b.failure
        if a.ok:
            np.testing.assert_allclose(a.features, b.features, rtol=1e-4, atol=1e-6)
    assert config_hash(sim.config, sim.identity_ignores) == config_hash(
        build_plugins({**base, "scheduling": "lockstep"}, feats)[0].config, sim.identity_ignores)


def test_process_executor_gives_each_worker_one_gpu(monkeypatch) -> None:
    import multiprocessing
    import os

    from invphys.plugins.executors import ProcessExecutor
    from invphys.plugins.executors.process import _init_worker, _terminate

    counter = multiprocessing.get_context("spawn").Value("i", 0)
    seen = []
    for _ in range(3):
        monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
        _init_worker({}, [3, 5], counter)
        seen.append(os.environ["CUDA_VISIBLE_DEVICES"])
    assert seen == ["3", "5", "3"]
    ex = ProcessExecutor(gpus=[3, 5])
    assert ex.workers == 2
    pool = ex._pool()
    try:
        got = {pool.submit(os.getenv, "CUDA_VISIBLE_DEVICES").result(timeout=120) for _ in range(4)}
    finally:
        _terminate(pool)
    assert got and got <= {"3", "5"}
