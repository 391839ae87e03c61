"""The cheese cut's committed protocol spec validates and asks for what the evaluation protocol requires."""

from __future__ import annotations

from pathlib import Path

from invphys.core.spec import load_spec

ROOT = Path(__file__).resolve().parent.parent
SPEC = ROOT / "examples" / "cheese_cut" / "invphys_cheese_cut" / "specs" / "protocol_quick.yaml"


def test_cheese_protocol_spec_meets_the_protocol() -> None:
    spec = load_spec(SPEC)
    assert spec.targets.selection == "farthest_point+random" and spec.targets.n >= 100
    assert spec.targets.validate_n >= 100  # every target validated through the simulator
    kinds = {b["type"] for b in spec.evaluation.baselines.values()}
    assert {"nearest_neighbour", "npe"} <= kinds and spec.evaluation.reference == "nearest_neighbour"
    assert spec.evaluation.noise_floor and spec.surrogate["type"] == "ensemble"
    assert spec.dataset.if_missing == "error" and (ROOT / spec.dataset.path).is_dir()
    assert spec.simulator["type"] == "cheese_cut" and spec.simulator["preset"] == "quick"
