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


def test_stages_that_read_targets_need_invert_and_invert_needs_answers():
    text = GOOD.replace("stages: [train, dataset, invert]", "stages: [dataset, train, report]")
    with pytest.raises(SpecError, match=r"stage 'report' reads the targets that 'invert' picks: add 'invert' to stages"):
        parse(text)
    no_optimizers = "\n".join(GOOD.splitlines()[:5]) + "\nstages: [dataset, train, invert, report]\n"
    with pytest.raises(SpecError, match=r"stage 'invert' needs an 'optimizers' section or evaluation.baselines"):
        parse(no_optimizers + "evaluation: {baselines: {}}\n")
    spec = parse(no_optimizers)  # the default baselines answer the targets that invert picks
    assert spec.stages == ["dataset", "train", "invert", "report"] and not spec.optimizers
    assert "nearest_neighbour" in spec.evaluation.baselines


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


# -- reliability (issue 12): safe loading, one name rule, one finite-number rule, cross-references ------
ROOT = __import__("pathlib").Path(__file__).resolve().parent.parent
COMMITTED_SPECS = sorted([*ROOT.glob("examples/orange_peel/invphys_orange_peel/specs/*.yaml"),
                          *ROOT.glob("datasets/specs/*.yaml")])


def test_schema_has_dialect_and_id_and_validates_the_committed_specs():
    import jsonschema
    import yaml

    schema = json_schema()
    assert schema["$schema"].endswith("2020-12/schema") and schema["$id"].startswith("urn:invphys:")
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    assert len(COMMITTED_SPECS) >= 4
    for path in COMMITTED_SPECS:
        errors = [f"{list(e.absolute_path)}: {e.message[:200]}" for e in validator.iter_errors(yaml.safe_load(path.read_text()))]
        assert not errors, f"{path}: {errors}"
    # a module:Class block that validate accepts is accepted by the schema too
    data = yaml.safe_load(GOOD)
    data["simulator"] = {"type": "core_plugins:LineSimulator", "frames": 4}
    parse(yaml.safe_dump(data))
    assert not list(validator.iter_errors(data))
    data["simulator"] = {"type": "not a path"}
    assert list(validator.iter_errors(data))


@pytest.mark.parametrize("label", ["../evil", "a/b", ".hidden", "-opt", "x" * 65, "con", "a b", "é"])
def test_labels_that_would_be_unsafe_paths_are_refused(label):
    text = GOOD.replace("  rs:\n", f"  {label!r}:\n")
    with pytest.raises(SpecError, match="not a safe name"):
        parse(text)


@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan", ".NaN"])
def test_non_finite_numbers_are_refused_with_their_path(value):
    with pytest.raises(SpecError, match=r"optimizers\.rs\.sigma0 \(line 10\): must be a finite number"):
        parse(GOOD.replace("sigma0: 0.2", f"sigma0: {value}"))


def test_duplicate_keys_alias_bombs_deep_nesting_and_binary_are_refused(tmp_path):
    with pytest.raises(SpecError, match=r"key 'seed' appears twice in one mapping \(lines 2 and 3\)"):
        parse("name: x\nseed: 1\nseed: 2\nsimulator: {type: test_line}\n")
    levels = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    levels += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 8)]
    with pytest.raises(SpecError, match="expands to more than"):
        parse("\n".join(levels) + "\n")
    with pytest.raises(SpecError, match="refers to the node that contains it"):
        parse("a: &a [1, *a]\n")
    with pytest.raises(SpecError, match="nested too deeply"):
        parse("a: " + "[" * 5000 + "]" * 5000 + "\n")
    (tmp_path / "bin.yaml").write_bytes(b"name: x\n\xff\xfe\n")
    with pytest.raises(SpecError, match=r"not UTF-8 text \(byte 0xff on line 2\)"):
        load_spec(tmp_path / "bin.yaml")
    with pytest.raises(SpecError, match="not a regular file"):
        load_spec("/dev/zero")
    with pytest.raises(SpecError, match="is a directory"):
        load_spec(tmp_path)
    big = tmp_path / "big.yaml"
    big.write_text("name: x\n# " + "y" * (2 << 20) + "\n")
    with pytest.raises(SpecError, match="over the"):
        load_spec(big)


def test_did_you_mean_for_top_level_and_section_keys():
    with pytest.raises(SpecError, match=r"optimisers \(line 6\): unknown field\. Did you mean 'optimizers'\?"):
        parse(GOOD.replace("optimizers:", "optimisers:"))
    with pytest.raises(SpecError, match=r"dataset\.sampel \(line 4\): unknown field\. Did you mean 'sampler'\?"):
        parse(GOOD.replace("sampler: sobol", "sampel: sobol"))


def test_several_problems_are_reported_at_once():
    text = GOOD.replace("n: 10", "n: 0, batch_size: -3, test_fraction: 1.5")
    with pytest.raises(SpecError) as err:
        parse(text)
    lines = str(err.value).splitlines()
    assert lines[0] == "spec.yaml: 3 problems" and len(lines) == 4
    assert "dataset.test_fraction (line 4): must be < 1" in lines[3]


def test_cross_references_known_without_training(tmp_path):
    with pytest.raises(SpecError, match=r"targets\.n \(line \d+\): 50 targets, but the held-out split has at most 2"):
        parse(GOOD + "targets: {n: 50}\n")
    with pytest.raises(SpecError, match=r"dataset\.path.*no dataset at"):
        parse(GOOD.replace("dataset: {n: 10, sampler: sobol}", f"dataset: {{path: '{tmp_path / 'nope'}'}}"))
    (tmp_path / "f").write_text("x")
    with pytest.raises(SpecError, match="is a file, not a dataset directory"):
        parse(GOOD.replace("dataset: {n: 10, sampler: sobol}", f"dataset: {{path: '{tmp_path / 'f'}'}}"))


# -- every problem at once, and what run would refuse (issues 47, 50) -------------------------------------
def test_shape_and_plugin_problems_come_together_in_file_order():
    """Before, a shape problem hid every plugin block's problem (one nesting level at a time)."""
    with pytest.raises(SpecError) as info:
        parse(GOOD.replace("seed: 3", "seed: -3").replace("frames: 4", "frames: 1")
              .replace("sigma0: 0.2", "sigma0: 0").replace("n: 10", "n: 0"))
    assert [".".join(p) for p, _ in info.value.problems] == ["seed", "dataset.n", "simulator.frames",
                                                              "optimizers.rs.sigma0"]
    text = str(info.value)
    assert text.startswith("spec.yaml: 4 problems") and text.index("seed (line 2)") < text.index(
        "simulator.frames (line 3)") < text.index("dataset.n (line 4)") < text.index("optimizers.rs.sigma0 (line 10)")


def test_a_non_text_key_is_one_problem_and_the_rest_is_still_checked():
    with pytest.raises(SpecError) as info:
        parse(GOOD.replace("seed: 3", "seed: 3\n1: x").replace("frames: 4", "frames: 1"))
    assert sorted(".".join(p) for p, _ in info.value.problems) == ["1", "simulator.frames"]


def test_output_problem_names_stores_bundles_files_and_loops(tmp_path):
    from invphys.core.spec import output_problem

    store, bundle = tmp_path / "store", tmp_path / "bundle"
    store.mkdir()
    (store / "_metadata.json").write_text("{}")
    bundle.mkdir()
    (bundle / "manifest.yaml").write_text("format_version: 2\n")
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "manifest.yaml").write_text("name: not a bundle\n")
    (tmp_path / "file").write_text("x")
    (tmp_path / "loop").symlink_to("loop")
    (tmp_path / "to_store").symlink_to(store)
    assert output_problem(tmp_path / "new" / "run") is None and output_problem(tmp_path / "plain" / "run") is None
    assert output_problem(store, store_ok=True) is None  # dataset generate resumes a store
    cases = {store / "run": "lies inside", store: "is a dataset store", bundle / "x": "an inverter bundle",
             tmp_path / "to_store" / "run": "a dataset store", tmp_path / "file": "is a file",
             tmp_path / "file" / "x": "which is a file", tmp_path / "loop": "symbolic-link loop",
             tmp_path / "loop" / "x": "symbolic-link loop"}
    for path, expect in cases.items():
        problem = output_problem(path)
        assert problem is not None and expect in problem, (path, problem)
    assert "lies inside" in (output_problem(store / "deeper", store_ok=True) or "")


#: every name the repository, its docs and tests import from invphys.core.spec (and the rest of the old module)
PUBLIC_NAMES = ("ActiveSection", "AdaptiveSection", "BUNDLE_MANIFEST", "DatasetSection", "EvaluationMethod",
                "EvaluationSection", "ExperimentSpec", "ExtraStore", "KEY_NEUTRAL_DEFAULTS", "Label", "MAX_DATASET_N",
                "MAX_SEED", "MAX_TARGETS", "MODULE_CLASS_PATTERN", "OPTIMIZER_RUNNER_KEYS", "ObjectiveSection",
                "PluginBlock", "PolishSection", "REPORT_FORMATS", "ReportFormat", "ReportSection", "SCHEMA_DIALECT",
                "SCHEMA_ID", "STAGES", "STORE_MARKERS", "TargetsSection", "TrackerSection", "check_output_directory",
                "json_schema", "load_spec", "optimizer_plugin_block", "output_problem", "parse_spec", "problem_line",
                "spec_problems", "validate_plugin_blocks", "validate_references", "validate_spec", "value_problems")


def test_every_public_name_keeps_its_import_path():
    import invphys.core.spec as spec

    assert [n for n in PUBLIC_NAMES if not hasattr(spec, n)] == []
    assert set(PUBLIC_NAMES) <= set(spec.__all__)


def test_the_spec_modules_are_small_with_short_functions():
    """No spec module over 600 lines, no function over 80 (spec.py was 968 lines)."""
    import ast
    from pathlib import Path

    import invphys.core.spec as spec

    files = sorted(Path(spec.__file__).parent.glob("spec*.py"))
    assert len(files) >= 6
    big = [(f.name, n) for f in files if (n := len(f.read_text().splitlines())) > 600]
    long = [(f.name, node.name, node.end_lineno - node.lineno + 1) for f in files
            for node in ast.walk(ast.parse(f.read_text())) if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            and node.end_lineno is not None and node.end_lineno - node.lineno + 1 > 80]
    assert (big, long) == ([], [])


def test_plugin_blocks_are_checked_by_the_registry_a_caller_passes():
    """core looks plugins up through what it is given (the process's registry by default, installed by it)."""
    from invphys.core.spec import validate_plugin_blocks
    from invphys.registry import Registry

    own = Registry(autoload=False)  # the built-ins only: test_random_search is not in it
    blocks = [("optimizers.rs", "optimizer", {"type": "test_random_search"})]
    assert validate_plugin_blocks(blocks) == []
    ((path, message),) = validate_plugin_blocks(blocks, own)
    assert path == ("optimizers", "rs", "type") and message.startswith("No optimizer named 'test_random_search'")


def test_without_a_plugin_lookup_the_checks_say_so_in_one_line(monkeypatch):
    from invphys.core import spec_lookup
    from invphys.core.errors import InvphysError
    from invphys.core.spec import validate_plugin_blocks

    monkeypatch.setattr(spec_lookup, "_default", None)
    with pytest.raises(InvphysError, match="no plugin registry") as err:
        validate_plugin_blocks([("simulator", "simulator", {"type": "test_line"})])
    assert "\n" not in str(err.value)
