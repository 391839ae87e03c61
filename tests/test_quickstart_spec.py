"""The quick start's spec (run by `make demo`) validates against the installed plugins and finds its data."""

from __future__ import annotations

from pathlib import Path

from invphys.core.dataset import DatasetStore
from invphys.core.spec import load_spec

ROOT = Path(__file__).resolve().parent.parent
QUICKSTART = ROOT / "examples" / "orange_peel" / "specs" / "quickstart.yaml"


def test_quickstart_spec_is_valid_and_its_dataset_is_committed():
    spec = load_spec(QUICKSTART)
    assert spec.stages == ["dataset", "train", "invert", "validate", "report"]
    assert spec.simulator["preset"] == "quick" and spec.simulator["arch"] == "cpu"
    store = DatasetStore(ROOT / spec.dataset.path)
    arrays = store.arrays(ok_only=True)
    assert len(arrays.theta) == 2000 and arrays.y.shape == (2000, 12)
    meta = store.metadata
    assert meta["identity"]["preset"] == "quick" and meta["identity"]["simulator"] == "orange_peel"
