"""The optional streaming hook: ``Simulator.simulate_stream`` (the default) and the local executor handing a
``native_stream`` simulator all its rows in one continuous-batching stream (the cheese cut's own stream:
examples/cheese_cut/tests/test_cheese_cut_stream.py)."""

from __future__ import annotations

import numpy as np
from test_dataset_toy import FEATURES, SIM, STREAMING, StreamingOscillator, ToyOscillator

from invphys.plugins.executors import LocalExecutor


def _params(n: int, seed: int = 1) -> np.ndarray:
    space = ToyOscillator().parameter_space()
    return space.denormalize(np.random.default_rng(seed).random((n, space.dim)))


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


def test_local_executor_hands_a_native_stream_all_its_rows_at_once() -> None:
    """Continuous batching: one stream over every row (not a stream per batch), rows taken in the order they
    come, each the row the batch API gives."""
    params = _params(5)
    StreamingOscillator.streams.clear()
    rows = list(LocalExecutor().run({"type": STREAMING, "substeps": 8}, {"type": FEATURES}, params, batch_size=2))
    assert StreamingOscillator.streams == [5]
    assert [i for i, _ in rows] == [4, 3, 2, 1, 0]
    batched = dict(LocalExecutor().run({"type": SIM, "substeps": 8}, {"type": FEATURES}, params, batch_size=2))
    for i, res in rows:
        assert res.ok and batched[i].ok and res.trajectory is None
        np.testing.assert_array_equal(res.features, batched[i].features)


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
