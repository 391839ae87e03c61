"""Continuous batching's queue order (``longest_first`` vs ``given``) and the engine's cost hook.

A run's result must not depend on the slot it ran in, the order of the queue or the runs beside it: on the
CPU with the serialised scatter every record (particles, series, force and work sums) is bit-identical in
both orders; only the order in which runs finish changes.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm import Engine, SceneError, streaming
from invphys_anisompm.streaming import queue_order
from invphys_anisompm.testing import build_scene

FRAMES = 4
SCENE = build_scene(settle_seconds=0.04)
E = [3e4, 9e5, 6e4, 2e5]   # row 1 is the costliest, row 0 the cheapest
MODEL = SCENE.model(len(E)).set_material("paste", E=E, eta=[0.02, 0.03, 0.01, 0.05])


def _assert_same_record(a, b) -> None:
    assert (a.failure, a.substeps, a.settle_substeps, a.frames) == (b.failure, b.substeps, b.settle_substeps, b.frames)
    for x, y in zip(a.positions + a.damage, b.positions + b.damage, strict=True):
        np.testing.assert_array_equal(x, y)
    assert set(a.series) == set(b.series)
    for name in a.series:
        np.testing.assert_array_equal(a.series_array(name), b.series_array(name), err_msg=name)


def test_queue_order_function() -> None:
    cost = np.array([5.0, 9.0, 5.0, 1.0])
    assert queue_order(cost, "longest_first").tolist() == [1, 0, 2, 3]   # ties keep row order
    assert queue_order(cost, "given").tolist() == [0, 1, 2, 3]
    rising = np.arange(1.0, 7.0)
    assert queue_order(rising, "longest_first", window=4).tolist() == [3, 2, 1, 0, 5, 4]   # LPT per window
    assert queue_order(rising, "longest_first", window=1).tolist() == list(range(6))
    assert queue_order(np.zeros(0), "longest_first", window=4).tolist() == []
    with pytest.raises(SceneError, match="unknown queue order 'shortest'"):
        queue_order(cost, "shortest")
    with pytest.raises(SceneError, match="known: longest_first, given"):
        Engine(SCENE).stream(MODEL, FRAMES, 2, 2, queue_order="random")


def test_one_slot_runs_in_queue_order_and_the_cost_hook_decides_it() -> None:
    engine = Engine(SCENE, backend="taichi", arch="cpu")
    cost = engine.estimate_cost(MODEL, FRAMES)
    assert cost[1] == cost.max() and cost[0] == cost.min() and len(set(cost)) > 2
    lpt = [i for i, _ in engine.stream(MODEL, FRAMES, 2, batch_size=1)]
    assert lpt == np.argsort(-cost, kind="stable").tolist()
    given = [i for i, _ in engine.stream(MODEL, FRAMES, 2, batch_size=1, queue_order="given")]
    assert given == [0, 1, 2, 3]
    # a scene may supply its own estimate: here the reverse of the row index
    hooked = Engine(SCENE, backend="taichi", arch="cpu", cost_estimator=lambda m, f: -np.arange(m.n_envs))
    assert [i for i, _ in hooked.stream(MODEL, FRAMES, 2, batch_size=1)] == [0, 1, 2, 3]


def test_results_do_not_depend_on_the_queue_order_or_slot() -> None:
    engine = Engine(SCENE, backend="taichi", arch="cpu")
    runs = {}
    for order in ("longest_first", "given"):
        stream = list(engine.stream(MODEL, FRAMES, 2, batch_size=2, queue_order=order))
        runs[order] = (dict(stream), [i for i, _ in stream])
    assert runs["longest_first"][1] != runs["given"][1]   # the runs really met other slots and partners
    assert sorted(runs["given"][0]) == [0, 1, 2, 3]
    plain = engine.run(MODEL, FRAMES, 2)
    for i in range(len(E)):
        _assert_same_record(runs["longest_first"][0][i], runs["given"][0][i])
        _assert_same_record(runs["given"][0][i], plain[i])


def test_longest_first_orders_within_windows_so_an_early_stop_ran_the_first_rows(monkeypatch) -> None:
    """A stream stopped early (a time-limited dataset session) must have run about the first rows of the
    design, not its costliest rows: ``longest_first`` sorts within windows of runs in row order."""
    monkeypatch.setattr(streaming, "QUEUE_WINDOW_PER_SLOT", 2)
    engine = Engine(SCENE, backend="taichi", arch="cpu")
    cost = engine.estimate_cost(MODEL, FRAMES)
    assert cost[1] > cost[0] and cost[3] > cost[2]
    assert [i for i, _ in engine.stream(MODEL, FRAMES, 2, batch_size=1)] == [1, 0, 3, 2]   # window of 2 runs
