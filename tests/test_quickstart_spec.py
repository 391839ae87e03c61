"""The quick starts' specs (`make demo`, `make demo-full`) validate against the installed plugins and find their
data; the demo validates few answers, on the simulator configuration that made its data."""

from __future__ import annotations

from pathlib import Path

from invphys.core.dataset import DatasetStore, RunIdentity
from invphys.core.spec import load_spec
from invphys.registry import Registry

ROOT = Path(__file__).resolve().parent.parent
SPECS = ROOT / "examples" / "orange_peel" / "invphys_orange_peel" / "specs"
QUICKSTART = SPECS / "quickstart.yaml"


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


def test_the_demo_validates_few_answers_with_the_data_s_simulator():
    """`make demo` runs in minutes on 2 CPU cores: its validate stage re-simulates at most 6 answers (2 targets
    x GC-PPO, warm start, lookup; the noise floor's runs are the renders' target runs), with the simulator
    configuration of the dataset (no validator overrides: the answers' R_actual compares like with like)."""
    spec = load_spec(QUICKSTART)
    answers = len(spec.optimizers) + len(spec.evaluation.baselines) + int(spec.evaluation.noise_floor)
    assert spec.targets.validate_n * answers <= 8 and not spec.evaluation.methods
    assert spec.targets.validate_n >= 2 and spec.report.render and spec.evaluation.noise_floor
    registry = Registry()
    validator = registry.create("validator", spec.validator)
    simulator = validator.simulator_for(registry.create("simulator", spec.simulator))
    stored = DatasetStore(ROOT / spec.dataset.path).metadata["identity"]
    assert RunIdentity.of(simulator).to_dict() == {k: stored[k] for k in ("simulator", "preset", "backend", "version",
                                                                          "config")}


def test_the_full_quick_start_is_one_spec_away():
    full = load_spec(SPECS / "quickstart_full.yaml")
    demo = load_spec(QUICKSTART)
    assert full.stages == demo.stages and full.simulator == demo.simulator and full.dataset == demo.dataset
    assert set(demo.optimizers) < set(full.optimizers) and full.targets.validate_n > demo.targets.validate_n
    assert "npe" in full.evaluation.baselines
    assert "quickstart_full.yaml" in (ROOT / "Makefile").read_text()
    assert "make demo-full" in (ROOT / "docs" / "getting-started.md").read_text()
