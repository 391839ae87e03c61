"""Executors end to end on a real (toy) simulator: local, process (spawn) and Ray give the same rows."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from test_dataset_toy import FEATURES, SIM, ToyOscillator

from invphys import registry
from invphys.core.dataset import DatasetStore
from invphys.data.generate import generate_dataset
from invphys.plugins.executors import LocalExecutor, ProcessExecutor, RayExecutor

TESTS = str(Path(__file__).resolve().parent)


def _params(n: int, seed: int = 3) -> np.ndarray:
    space = ToyOscillator().parameter_space()
    return space.denormalize(np.random.default_rng(seed).random((n, space.dim)))


def _collect(executor, sim: dict, params: np.ndarray, batch_size: int) -> dict[int, object]:
    out = {}
    for i, res in executor.run(sim, {"type": FEATURES}, params, batch_size):
        assert i not in out, "a row was yielded twice"
        out[i] = res
    assert sorted(out) == list(range(len(params)))
    return out


def _assert_same(a: dict, b: dict) -> None:
    for i in a:
        assert a[i].ok == b[i].ok
        assert a[i].failure == b[i].failure
        if a[i].ok:
            np.testing.assert_array_equal(a[i].features, b[i].features)
        assert a[i].trajectory is None and b[i].trajectory is None


def test_executors_are_registered_and_import_cheap() -> None:
    assert {"local", "process", "ray"} <= set(registry.names("executor"))
    assert registry.get("executor", "process") is ProcessExecutor


def test_local_and_process_executors_agree_and_isolate_exceptions() -> None:
    sim = {"type": SIM, "substeps": 1, "raise_c_above": 0.6}
    params = _params(24)
    local = _collect(LocalExecutor(), sim, params, batch_size=5)
    n_raised = sum(1 for r in local.values() if not r.ok and "exploded" in (r.failure or ""))
    n_blown = sum(1 for r in local.values() if not r.ok and "blow-up" in (r.failure or ""))
    raised_rows = params[:, 1] > 0.6
    assert n_raised == raised_rows.sum() > 0  # only the raising rows fail, not their batch neighbours
    assert n_blown > 0 and sum(r.ok for r in local.values()) > 0
    for i in np.flatnonzero(raised_rows):
        assert local[i].failure.startswith("RuntimeError: toy oscillator exploded")
    proc = _collect(ProcessExecutor(workers=2), sim, params, batch_size=5)
    _assert_same(local, proc)


def test_process_executor_survives_a_worker_that_dies() -> None:
    sim = {"type": SIM, "substeps": 8, "crash_c_above": 0.8}  # stable steps: only crashes fail
    params = _params(12, seed=5)
    crashing = params[:, 1] > 0.8
    assert 0 < crashing.sum() < len(params)
    got = _collect(ProcessExecutor(workers=2, max_in_flight=2), sim, params, batch_size=3)
    for i, res in got.items():
        if crashing[i]:
            assert not res.ok and res.failure.startswith("worker process died")
        else:
            assert res.ok, res.failure  # neighbours of the crashing row are re-run, not failed


def test_ray_executor_end_to_end(tmp_path, monkeypatch) -> None:
    pytest.importorskip("ray")
    # local Ray workers inherit the driver's environment: make the toy plugin importable there
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")]))
    import ray

    sim = {"type": SIM, "substeps": 1, "raise_c_above": 0.6}
    params = _params(24)
    local = _collect(LocalExecutor(), sim, params, batch_size=5)
    try:
        # the executor starts a local instance (kept for the next steps: shutdown=False)
        got = _collect(RayExecutor(num_cpus=1, max_in_flight=2, max_retries=1, shutdown=False), sim, params,
                       batch_size=5)
        assert ray.is_initialized()
        _assert_same(local, got)
        # a task whose worker dies is retried, then its batch is re-run row by row: only the bad row fails
        crash = {"type": SIM, "substeps": 8, "crash_c_above": 0.8}
        cparams = _params(12, seed=5)[:6]
        crashing = cparams[:, 1] > 0.8
        assert crashing.sum() == 1
        got = _collect(RayExecutor(max_retries=0), crash, cparams, batch_size=3)
        for i, res in got.items():
            assert res.ok != crashing[i]
            if crashing[i]:
                assert res.failure.startswith("ray task failed")
        # and through the generation loop into a store
        summary = generate_dataset(tmp_path / "ds", {"type": SIM, "substeps": 1}, n=16, batch_size=4,
                                   executor={"type": "ray", "max_in_flight": 2}, progress=False)
    finally:
        ray.shutdown()
    assert summary.ran == 16 and summary.ok + summary.failed == 16 and summary.failed > 0
    store = DatasetStore(tmp_path / "ds")
    assert len(store.frame()) == 16 and len(store.arrays().theta) == summary.ok
