"""The cheese cut's own stream (``simulate_stream`` on its warm engine, ``scheduling: continuous``): the local
executor hands it every row at once, and its runs are the lock-step ones (the framework side, with a toy:
tests/test_executors_stream.py)."""

from __future__ import annotations

import numpy as np
import pytest

from invphys.core.dataset import config_hash
from invphys.plugins.executors import LocalExecutor
from invphys.plugins.executors._batch import build_plugins


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
