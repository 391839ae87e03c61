"""A dataset made by spawned worker processes (the process executor) into a store: its rows and columns, its
identity (a hash of the whole config, less the fields the simulator lists in ``identity_ignores``), then
resumed with a larger n in this process (only the new rows run)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from test_dataset_toy import FEATURES, ToyOscillator

from invphys import registry
from invphys.core.dataset import DatasetStore, RunIdentity
from invphys.data.generate import generate_dataset

SIM = "test_dataset_process_workers:PacedOscillator"  # spawn workers import it by this path


class PacedOscillator(ToyOscillator):
    """The toy oscillator whose ``sleep_s`` (how fast it runs, not what it gives) is not part of a run."""

    name = "paced_oscillator"
    identity_ignores = ("sleep_s",)


def test_process_workers_fill_a_store_that_resumes(tmp_path) -> None:
    reg = registry.default_registry()
    sim = {"type": SIM, "n_frames": 20, "substeps": 8}
    path = tmp_path / "store"
    first = generate_dataset(path, sim, n=4, batch_size=2, seed=2,
                             executor={"type": "process", "workers": 2}, progress=False)
    assert first.ran == 4 and first.complete
    df = pd.read_parquet(path)
    assert len(df) == 4 and df["key"].is_unique
    assert set(df["preset"]) == {"tiny"} and set(df["backend"]) == {"numpy"}
    assert (df["substeps"] > 0).all() and (df["wall_time_s"] > 0).all()
    meta = DatasetStore(path).metadata
    config = RunIdentity.of(reg.create("simulator", sim)).config  # a hash of the whole config
    assert meta["identity"] == {"simulator": "paced_oscillator", "preset": "tiny", "backend": "numpy",
                                "version": meta["simulator"]["version"], "config": config}
    # a field in identity_ignores is not part of the identity (same rows); any other field is
    assert RunIdentity.of(reg.create("simulator", {**sim, "sleep_s": 0.01})).config == config
    assert RunIdentity.of(reg.create("simulator", {**sim, "n_frames": 19})).config != config
    assert meta["extractor_block"] == {"type": FEATURES}
    arr = DatasetStore(path).arrays()
    assert arr.theta.shape == (first.ok, 3) and arr.y.shape[1] == len(meta["feature_names"]) == 5
    assert first.ok > 0 and np.isfinite(arr.y).all()
    # resuming with a larger n simulates only the new rows, in this process (local executor)
    more = generate_dataset(path, sim, n=5, batch_size=2, seed=2, progress=False)
    assert more.already_present == 4 and more.ran == 1
    assert len(pd.read_parquet(path)) == 5
