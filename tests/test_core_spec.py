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
executor: {type: core_plugins:LineSimulator}
dataset: {n: 10, sampler: sobol}
surrogate: {type: core_plugins:LineSimulator}
optimizers:
  rs:
    type: test_random_search
    space: raw
    sigma0: 0.2
stages: [train, dataset]
"""


@pytest.fixture(autouse=True)
def plugins():
    with registry.registered(LineSimulator, RandomSearch):
        yield


def parse(text: str):
    return parse_spec(textwrap.dedent(text), source="spec.yaml")


def good_without(*drop: str) -> str:
    return "\n".join(line for line in GOOD.splitlines() if not any(line.startswith(d) for d in drop)) + "\n"


def test_good_spec_round_trip(tmp_path):
    text = good_without("executor", "surrogate") + "surrogate: {type: test_line}\n"
    # surrogate must be a surrogate plugin: test_line is a simulator, so pass 2 complains
    with pytest.raises(SpecError, match="No surrogate named 'test_line'"):
        parse(text)
    ok = good_without("executor", "surrogate", "stages", "optimizers", "  ") + "stages: [dataset]\n"
    path = tmp_path / "s.yaml"
    path.write_text(ok)
    spec = load_spec(path)
    assert spec.name == "demo" and spec.seed == 3 and spec.dataset.sampler == "sobol"
    assert spec.executor == {"type": "local"} and spec.stages == ["dataset"]


def test_stage_order_is_canonical():
    spec = parse(good_without("executor", "surrogate", "stages", "optimizers", "  ") + "stages: [dataset]\n")
    assert spec.stages == ["dataset"]


def test_misspelled_plugin_did_you_mean_with_line():
    text = GOOD.replace("type: test_random_search", "type: test_random_serch")
    text = good_without("executor", "surrogate").replace("type: test_random_search", "type: test_random_serch")
    with pytest.raises(SpecError) as err:
        parse(text)
    msg = str(err.value)
    assert "optimizers.rs.type (line 6): No optimizer named 'test_random_serch'. Did you mean 'test_random_search'?" in msg


def test_bad_field_value_reported_by_path_and_line():
    text = good_without("executor", "surrogate", "stages").replace("sigma0: 0.2", "sigma0: -1")
    with pytest.raises(SpecError) as err:
        parse(text)
    assert "optimizers.rs.sigma0 (line 9): must be > 0" in str(err.value)


def test_unknown_field_in_plugin_block_suggests_name():
    text = good_without("executor", "surrogate", "stages").replace("sigma0: 0.2", "sigma: 0.2")
    with pytest.raises(SpecError, match=r"optimizers\.rs\.sigma \(line 9\): unknown field\. Did you mean 'sigma0'\?"):
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
    text = good_without("executor", "surrogate", "stages").replace("space: raw", "space: flow")
    text += "surrogate: {type: core_plugins:RandomSearch}\n"
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
