"""The committed protocol specs validate and ask for what the evaluation protocol requires."""

from __future__ import annotations

from pathlib import Path

import pytest

from invphys.core.errors import SpecError
from invphys.core.spec import load_spec, parse_spec

ROOT = Path(__file__).resolve().parent.parent
SPECS = sorted((ROOT / "examples" / "orange_peel" / "invphys_orange_peel" / "specs").glob("protocol*.yaml"))
assert len(SPECS) == 3, "the protocol specs moved: update SPECS"


@pytest.mark.parametrize("path", SPECS, ids=lambda p: p.name)
def test_protocol_specs_meet_the_protocol(path: Path) -> None:
    spec = load_spec(path)
    assert spec.targets.selection == "farthest_point+random" and spec.targets.n >= 100
    assert spec.targets.validate_n >= 100  # every target validated through the simulator
    kinds = {b["type"] for b in spec.evaluation.baselines.values()}
    assert {"nearest_neighbour", "npe"} <= kinds and spec.evaluation.reference == "nearest_neighbour"
    assert spec.surrogate["type"] == "ensemble"
    assert {"simulator", "surrogate"} <= {m.evaluator for m in spec.evaluation.methods.values()}
    assert Path(ROOT / spec.dataset.path).name.startswith("orange_peel_")


def test_evaluation_section_errors_are_one_clear_line() -> None:
    base = "name: x\nsimulator: {type: 'test_dataset_toy:ToyOscillator'}\nsurrogate: {type: mlp}\n" \
           "optimizers: {cma: {type: cma_es}}\n"
    with pytest.raises(SpecError, match=r"evaluation\.methods\.m\.start.*'nearest_neighbor'.*Did you mean"):
        parse_spec(base + "evaluation: {methods: {m: {start: nearest_neighbor}}}\n")
    with pytest.raises(SpecError, match="used twice"):
        parse_spec(base + "evaluation: {baselines: {cma: {type: nearest_neighbour}}}\n")
    with pytest.raises(SpecError, match=r"evaluation\.baselines\.nn\.k"):
        parse_spec(base + "evaluation: {baselines: {nn: {type: nearest_neighbour, k: 0}}}\n")
    spec = parse_spec(base)
    assert set(spec.evaluation.baselines) == {"nearest_neighbour", "npe"}  # baselines by default
