"""The quick start's spec (run by `make demo`) validates against the installed plugins and finds its data."""

from __future__ import annotations

from pathlib import Path

from invphys.core.dataset import DatasetStore
from invphys.core.spec import load_spec

ROOT = Path(__file__).resolve().parent.parent
QUICKSTART = ROOT / "examples" / "orange_peel" / "invphys_orange_peel" / "specs" / "quickstart.yaml"


def test_quickstart_spec_is_valid_and_its_dataset_is_committed():
    spec = load_spec(QUICKSTART)
    assert spec.stages == ["dataset", "train", "invert", "validate", "report"]
    assert spec.simulator["preset"] == "quick" and spec.simulator["arch"] == "cpu"
    store = DatasetStore(ROOT / spec.dataset.path)
    arrays = store.arrays(ok_only=True)
    assert len(arrays.theta) == 2000 and arrays.y.shape == (2000, 12)
    meta = store.metadata
    assert meta["identity"]["preset"] == "quick" and meta["identity"]["simulator"] == "orange_peel"


def test_paper_spec_is_valid_and_names_every_method_of_the_paper():
    spec = load_spec(ROOT / "examples" / "orange_peel" / "invphys_orange_peel" / "specs" / "paper.yaml")
    types = {b["type"] for b in spec.optimizers.values()}
    assert types == {"cma_es", "ppo", "gc_ppo", "warm_start"}
    assert {b.get("space", "raw") for b in spec.optimizers.values()} == {"raw", "flow", "vae"}
    assert spec.targets.n == 20 and spec.targets.validate_n == 10
    assert DatasetStore(ROOT / spec.dataset.path).arrays().theta.shape == (2000, 9)
