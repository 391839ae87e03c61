"""YAML experiment specs: two-pass validation, error paths and lines, JSON Schema."""

from __future__ import annotations

import textwrap

import pytest
from core_plugins import LineSimulator, RandomSearch

from invphys import registry
from invphys.core.errors import SpecError
from invphys.core.spec import json_schema, load_spec, parse_spec

GOOD = """\
name: demo
seed: 3
simulator: {type: test_line, frames: 4}
dataset: {n: 10, sampler: sobol}
surrogate: {type: mlp}
optimizers:
  rs:
    type: test_random_search
    space: raw
    sigma0: 0.2
stages: [train, dataset, invert]
"""


@pytest.fixture(autouse=True)
def plugins():
    with registry.registered(LineSimulator, RandomSearch):
        yield


def parse(text: str):
    return parse_spec(textwrap.dedent(text), source="spec.yaml")


def test_good_spec_round_trip(tmp_path):
    path = tmp_path / "s.yaml"
    path.write_text(GOOD)
    spec = load_spec(path)
    assert spec.name == "demo" and spec.seed == 3 and spec.dataset.sampler == "sobol"
    assert spec.executor == {"type": "local"}
    assert spec.stages == ["dataset", "train", "invert"]  # pipeline order
    assert [p for p, _, _ in spec.plugin_blocks()] == ["simulator", "executor", "surrogate", "optimizers.rs"]
    # runner-level keys are not passed to the optimizer's Config
    assert spec.plugin_blocks()[-1][2] == {"type": "test_random_search", "sigma0": 0.2}


def test_wrong_kind_is_reported():
    with pytest.raises(SpecError, match=r"surrogate\.type \(line 5\): No surrogate named 'test_line'"):
        parse(GOOD.replace("surrogate: {type: mlp}", "surrogate: {type: test_line}"))


def test_default_stages_follow_the_sections_present():
    spec = parse("name: x\nsimulator: {type: test_line}\n")
    assert spec.stages == ["dataset"]
    spec = parse(GOOD.replace("stages: [train, dataset, invert]\n", ""))
    assert spec.stages == ["dataset", "train", "invert", "report"]


def test_misspelled_plugin_did_you_mean_with_line():
    text = GOOD.replace("type: test_random_search", "type: test_random_serch")
    with pytest.raises(SpecError) as err:
        parse(text)
    msg = str(err.value)
    assert "optimizers.rs.type (line 8): No optimizer named 'test_random_serch'. Did you mean 'test_random_search'?" in msg


def test_bad_field_value_reported_by_path_and_line():
    text = GOOD.replace("sigma0: 0.2", "sigma0: -1")
    with pytest.raises(SpecError) as err:
        parse(text)
    assert "optimizers.rs.sigma0 (line 10): must be > 0" in str(err.value)


def test_unknown_field_in_plugin_block_suggests_name():
    text = GOOD.replace("sigma0: 0.2", "sigma: 0.2")
    with pytest.raises(SpecError, match=r"optimizers\.rs\.sigma \(line 10\): unknown field\. Did you mean 'sigma0'\?"):
        parse(text)


def test_shape_errors():
    with pytest.raises(SpecError, match=r"dataset\.n \(line 2\): must be > 0"):
        parse("name: x\ndataset: {n: 0}\nsimulator: {type: test_line}\nstages: [dataset]\n")
    with pytest.raises(SpecError, match=r"simulator: required field is missing"):
        parse("name: x\n")
    with pytest.raises(SpecError, match=r"unknown stage 'trian'\. Did you mean 'train'"):
        parse("name: x\nsimulator: {type: test_line}\nstages: [trian]\n")
    with pytest.raises(SpecError, match="stage 'train' needs a 'surrogate' section"):
        parse("name: x\nsimulator: {type: test_line}\nstages: [train]\n")
    with pytest.raises(SpecError, match="not valid YAML"):
        parse("name: [x\n")
    with pytest.raises(SpecError, match="a spec is a YAML mapping"):
        parse("- 1\n")


def test_latent_space_label_checked():
    text = GOOD.replace("space: raw", "space: flow")
    with pytest.raises(SpecError, match="'flow' is neither 'raw' nor a latent model label"):
        parse(text)


def test_missing_file_is_a_spec_error(tmp_path):
    with pytest.raises(SpecError, match="cannot read spec"):
        load_spec(tmp_path / "nope.yaml")


def test_json_schema_covers_installed_plugins():
    schema = json_schema()
    titles = [s["title"] for s in schema["$defs"]["optimizer_block"]["oneOf"]]
    assert "optimizer:test_random_search" in titles
    block = next(s for s in schema["$defs"]["optimizer_block"]["oneOf"] if s["title"].endswith("test_random_search"))
    assert block["properties"]["sigma0"]["exclusiveMinimum"] == 0
    assert "simulator:test_line" in [s["title"] for s in schema["$defs"]["simulator_block"]["oneOf"]]
