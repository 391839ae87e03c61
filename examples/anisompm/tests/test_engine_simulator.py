"""The engine simulator base: both foods use it, their engine knobs may be one ``engine:`` block, and the
canonical (flat) config keeps the config hashes that committed datasets and bundles recorded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from invphys_anisompm.simulator import EngineSimulator
from invphys_cheese_cut.simulator import CheeseCutSimulator
from invphys_orange_peel.simulator import OrangePeelSimulator
from pydantic import ValidationError

from invphys.core.store.keys import RunIdentity

ROOT = Path(__file__).resolve().parents[3]
FOODS = (OrangePeelSimulator, CheeseCutSimulator)


@pytest.mark.parametrize("cls", FOODS)
def test_both_foods_are_engine_simulators(cls) -> None:
    assert issubclass(cls, EngineSimulator)
    for key in ("backend", "arch", "batch_size", "scheduling", "cfl", "max_substeps_per_frame", "deterministic"):
        assert key in cls.Config.engine_keys()
    assert "preset" not in cls.Config.engine_keys() and "record_every" not in cls.Config.engine_keys()


@pytest.mark.parametrize("cls", FOODS)
def test_engine_block_equals_flat_keys(cls) -> None:
    flat = cls(preset="tiny", backend="taichi", arch="cpu", batch_size=8, cfl=0.5, damage=False)
    block = cls(preset="tiny", engine={"backend": "taichi", "arch": "cpu", "batch_size": 8, "cfl": 0.5,
                                       "damage": False})
    assert block.config.model_dump() == flat.config.model_dump()
    assert "engine" not in block.config.model_dump()
    assert RunIdentity.of(block) == RunIdentity.of(flat)


@pytest.mark.parametrize("cls", FOODS)
def test_a_flat_key_wins_over_the_block(cls) -> None:
    sim = cls({"preset": "tiny", "engine": {"arch": "cuda", "cfl": 0.5}}, arch="cpu")
    assert (sim.config.arch, sim.config.cfl) == ("cpu", 0.5)


@pytest.mark.parametrize("cls", FOODS)
def test_engine_block_errors_name_the_key(cls) -> None:
    with pytest.raises(ValidationError, match=r"engine\.cfl"):
        cls(engine={"cfl": -1})
    with pytest.raises(ValidationError, match=r"engine\.preset"):  # a food's own key is not the engine's
        cls(engine={"preset": "tiny"})


@pytest.mark.parametrize("name", ["orange_peel_quick", "cheese_cut_quick"])
def test_committed_datasets_keep_their_identity(name) -> None:
    meta = json.loads((ROOT / "datasets" / name / "_metadata.json").read_text())
    block = dict(meta["simulator_block"])
    block.pop("type")
    cls = {"orange_peel": OrangePeelSimulator, "cheese_cut": CheeseCutSimulator}[meta["identity"]["simulator"]]
    assert RunIdentity.of(cls(block)).to_dict() == meta["identity"]
    keys = set(cls.Config.engine_keys())
    nested = {k: v for k, v in block.items() if k not in keys} | {"engine": {k: v for k, v in block.items() if k in keys}}
    assert RunIdentity.of(cls(nested)).to_dict() == meta["identity"]


def test_shipped_bundle_config_keeps_its_identity() -> None:
    manifest = yaml.safe_load((ROOT / "inverters" / "cheese_cut_quick" / "manifest.yaml").read_text())
    block = {k: v for k, v in manifest["simulator"]["config"].items() if k != "type"}
    assert RunIdentity.of(CheeseCutSimulator(block)).config == "6fa4f298ef7966a1"


def test_the_base_runs_a_food_both_ways() -> None:
    """Lockstep and continuous batching through the base give the same results (cheese, tiny, CPU)."""
    sim = CheeseCutSimulator(preset="tiny", engine={"arch": "cpu", "batch_size": 2})
    x = sim.parameter_space().denormalize(np.random.default_rng(0).random((3, 7)))
    lock = sim.simulate(x)
    streamed = dict(sim.simulate_stream(x))
    assert [r.ok for r in lock] == [streamed[i].ok for i in range(3)]
    for i, r in enumerate(lock):
        if r.ok:
            np.testing.assert_array_equal(r.trajectory.positions, streamed[i].trajectory.positions)
    assert sim.estimate_cost(x).shape == (3,)


def test_canonical_block_folds_the_engine_block() -> None:
    block = {"type": "cheese_cut", "preset": "tiny", "arch": "cpu", "engine": {"arch": "cuda", "batch_size": 4}}
    assert CheeseCutSimulator.canonical_block(block) == {"type": "cheese_cut", "preset": "tiny", "arch": "cpu",
                                                         "batch_size": 4}
    flat = {"type": "cheese_cut", "preset": "tiny"}
    assert CheeseCutSimulator.canonical_block(flat) == flat


def test_stage_keys_are_the_same_for_an_engine_block_and_flat_keys() -> None:
    """A spec written with ``engine:`` reuses the cached stages of the same spec written flat, and the engine's
    execution knobs (arch, batch size) stay out of the keys in both forms."""
    from pathlib import Path

    import invphys_orange_peel
    import yaml

    from invphys import registry
    from invphys.core.spec import validate_spec
    from invphys.pipeline import cache

    spec_file = Path(invphys_orange_peel.__file__).parent / "specs" / "quickstart.yaml"
    flat = yaml.safe_load(spec_file.read_text())
    flat["simulator"] = {**flat["simulator"], "arch": "cpu", "batch_size": 4}
    nested = dict(flat)
    sim = dict(flat["simulator"])
    nested["simulator"] = {"type": sim.pop("type"), "preset": sim.pop("preset", "quick"),
                           "engine": {"arch": sim.pop("arch"), "batch_size": sim.pop("batch_size")}, **sim}
    other = dict(flat)
    other["simulator"] = {**flat["simulator"], "arch": "cuda", "batch_size": 64}
    reg = registry.default_registry()

    def key(data: dict) -> str:
        return cache.digest(cache.key_inputs(validate_spec(data), ("simulator",), reg))

    assert key(flat) == key(nested) == key(other)


def test_an_open_feed_gives_the_results_of_a_closed_stream() -> None:
    """``simulate_feed`` on the warm engine: rows fed in pieces while others run (and an empty poll in
    between) come back numbered in feed order, equal to the same rows simulated in one call (cheese, tiny)."""
    sim = CheeseCutSimulator(preset="tiny", engine={"arch": "cpu", "batch_size": 2})
    assert sim.native_feed
    x = sim.parameter_space().denormalize(np.random.default_rng(1).random((4, 7)))
    pieces = [x[:1], None, x[1:3], x[3:]]

    def feeder(free: int) -> np.ndarray | None:
        return pieces.pop(0) if pieces else None

    fed = dict(sim.simulate_feed(feeder))
    assert sorted(fed) == [0, 1, 2, 3]
    for i, r in enumerate(sim.simulate(x)):
        assert r.ok == fed[i].ok
        if r.ok:
            np.testing.assert_array_equal(r.trajectory.positions, fed[i].trajectory.positions)
