"""The real orange-peel simulator (tiny preset) through the process executor (spawn: taichi is
initialised in fresh workers) into a store, then resumed."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from invphys import registry
from invphys.core.dataset import DatasetStore, RunIdentity
from invphys.data.generate import generate_dataset
from invphys.registry import AUTOLOAD_ENV

pytest.importorskip("invphys_orange_peel")
pytest.importorskip("taichi")


@pytest.mark.slow
def test_orange_peel_tiny_dataset_with_process_workers(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv(AUTOLOAD_ENV, raising=False)  # spawn workers find the plugin by its entry point
    reg = registry.default_registry()
    if "orange_peel" not in reg.names("simulator"):
        import invphys_orange_peel.plugin as plugin

        reg.register(plugin, "invphys-orange-peel")
    sim = {"type": "orange_peel", "preset": "tiny", "arch": "cpu", "batch_size": 2, "frames": 48}
    path = tmp_path / "peel"
    first = generate_dataset(path, sim, n=4, batch_size=2, seed=2,
                             executor={"type": "process", "workers": 2}, progress=False)
    assert first.ran == 4 and first.complete
    df = pd.read_parquet(path)
    assert len(df) == 4 and df["key"].is_unique
    assert set(df["preset"]) == {"tiny"} and set(df["backend"]) == {"taichi"}
    assert (df["substeps"] > 0).all() and (df["wall_time_s"] > 0).all()
    meta = DatasetStore(path).metadata
    config = RunIdentity.of(reg.create("simulator", sim)).config  # a hash of the whole config
    assert meta["identity"] == {"simulator": "orange_peel", "preset": "tiny", "backend": "taichi",
                                "version": meta["simulator"]["version"], "config": config}
    # the device and launch batching are not part of the identity (identity_ignores): same rows
    assert RunIdentity.of(reg.create("simulator", {**sim, "arch": "auto", "batch_size": 8})).config == config
    assert RunIdentity.of(reg.create("simulator", {**sim, "frames": 47})).config != config
    assert meta["extractor_block"] == {"type": "orange_peel_features"}
    arr = DatasetStore(path).arrays()
    assert arr.theta.shape == (first.ok, 9) and arr.y.shape[1] == len(meta["feature_names"]) >= 12
    assert np.isfinite(arr.y).all()
    # resuming with a larger n simulates only the new rows, in this process (local executor)
    more = generate_dataset(path, sim, n=5, batch_size=2, seed=2, progress=False)
    assert more.already_present == 4 and more.ran == 1
    assert len(pd.read_parquet(path)) == 5
