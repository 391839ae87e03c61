"""The stage runner: caching by fingerprint, re-running what changed, and the dataset fallback."""

from __future__ import annotations

import json

from test_dataset_toy import ToyOscillator

from invphys.core.spec import parse_spec
from invphys.pipeline.runner import run_spec

SPEC = """\
name: runner-test
seed: 1
simulator: {type: "test_dataset_toy:ToyOscillator", n_frames: 10}
dataset: {n: 6, batch_size: 3}
stages: [dataset]
"""


def events_of(spec_text, out, **kwargs):
    events = []
    run_spec(parse_spec(spec_text), out, progress=False,
             on_stage=lambda stage, status, summary: events.append((stage, status)), **kwargs)
    return events


def test_rerun_is_cached_and_a_changed_section_reruns(tmp_path):
    out = tmp_path / "run"
    assert events_of(SPEC, out) == [("dataset", "start"), ("dataset", "done")]
    first = json.loads((out / "dataset" / "summary.json").read_text())
    assert first["ok"] == 6
    assert events_of(SPEC, out) == [("dataset", "cached")]
    # more rows: the stage runs again and resumes, simulating only the 3 new points
    assert events_of(SPEC.replace("n: 6", "n: 9"), out) == [("dataset", "start"), ("dataset", "done")]
    summary = json.loads((out / "dataset" / "summary.json").read_text())
    assert summary["already_present"] == 6 and summary["ran"] == 3
    # force re-runs a cached stage
    assert events_of(SPEC.replace("n: 6", "n: 9"), out, force=["dataset"])[0] == ("dataset", "start")
    assert (out / "spec.yaml").exists()


def test_missing_dataset_path_falls_back_to_generating(tmp_path):
    missing = tmp_path / "absent_store"
    text = SPEC.replace("dataset: {n: 6, batch_size: 3}",
                        f"dataset: {{n: 4, batch_size: 2, path: '{missing}', if_missing: generate}}")
    out = tmp_path / "run"
    events_of(text, out)
    summary = json.loads((out / "dataset" / "summary.json").read_text())
    assert summary["generated"] and summary["ok"] == 4
    assert summary["path"] == str(out / "dataset" / "store") and not missing.exists()


def test_existing_dataset_path_is_used_not_generated(tmp_path):
    out1 = tmp_path / "first"
    events_of(SPEC, out1)
    store = out1 / "dataset" / "store"
    text = SPEC.replace("dataset: {n: 6, batch_size: 3}", f"dataset: {{path: '{store}'}}")
    events_of(text, tmp_path / "second")
    summary = json.loads((tmp_path / "second" / "dataset" / "summary.json").read_text())
    assert summary["generated"] is False and summary["ok"] == 6


def test_train_reruns_when_its_dataset_changes_and_says_why(tmp_path):
    """Stale results (issue 12): rows added to a store that dataset.path names re-run every stage that
    read it, even though the spec did not change."""
    from rich.console import Console

    from invphys.data.generate import generate_dataset

    store = tmp_path / "store"
    sim = {"type": "test_dataset_toy:ToyOscillator", "n_frames": 10}
    generate_dataset(store, sim, n=10, batch_size=5, seed=1, progress=False)
    text = SPEC.replace("dataset: {n: 6, batch_size: 3}", f"dataset: {{path: '{store}'}}").replace(
        "stages: [dataset]", "surrogate: {type: mlp, max_epochs: 2, hidden: [4, 4, 4], batch_size: 4}\n"
        "stages: [dataset, train]")
    out = tmp_path / "run"
    assert events_of(text, out) == [("dataset", "start"), ("dataset", "done"), ("train", "start"), ("train", "done")]
    assert events_of(text, out) == [("dataset", "cached"), ("train", "cached")]
    generate_dataset(store, sim, n=15, batch_size=5, seed=1, progress=False)  # 5 more rows
    console = Console(record=True, width=200)
    events = []
    run_spec(parse_spec(text), out, progress=False, console=console,
             on_stage=lambda stage, status, summary: events.append((stage, status)))
    assert events == [("dataset", "start"), ("dataset", "done"), ("train", "start"), ("train", "done")]
    assert "re-running: dataset content changed" in console.export_text()
    assert json.loads((out / "dataset" / "summary.json").read_text())["ok"] == 15
    # forcing train re-runs nothing before it, and a later stage would see train's new run id
    done = json.loads((out / "train" / "DONE.json").read_text())
    assert events_of(text, out, force=["train"]) == [("dataset", "cached"), ("train", "start"), ("train", "done")]
    assert json.loads((out / "train" / "DONE.json").read_text())["run_id"] != done["run_id"]


def test_a_stage_run_alone_warns_when_an_earlier_stage_no_longer_matches(tmp_path):
    """Running one stage (--stage) over an earlier stage that the spec or data has moved past says so."""
    from rich.console import Console

    text = SPEC.replace("n: 6", "n: 12").replace(
        "stages: [dataset]", "surrogate: {type: mlp, max_epochs: 2, hidden: [4, 4, 4], batch_size: 4}\n"
        "stages: [dataset, train]")
    out = tmp_path / "run"
    events_of(text, out)
    console = Console(record=True, width=300)
    run_spec(parse_spec(text.replace("n: 12", "n: 14")), out, stages=["train"], progress=False, console=console)
    said = console.export_text()
    assert "warning: train: reads results that no longer match the spec or data: dataset (spec sections changed)" in said
    console = Console(record=True, width=300)  # all current: no warning
    run_spec(parse_spec(text), out, stages=["train"], force=["train"], progress=False, console=console)
    assert "warning" not in console.export_text()


def test_run_refuses_bad_out_and_stage_names_and_survives_a_broken_marker(tmp_path):
    import pytest

    from invphys.core.errors import InvphysError

    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(InvphysError, match="is a file"):
        run_spec(parse_spec(SPEC), afile, progress=False)
    assert afile.read_text() == "x"
    with pytest.raises(InvphysError, match="Did you mean 'dataset'"):
        run_spec(parse_spec(SPEC), tmp_path / "r", stages=["datset"], progress=False)
    out = tmp_path / "run"
    events_of(SPEC, out)
    (out / "dataset" / "DONE.json").write_text("{not json")
    assert events_of(SPEC, out) == [("dataset", "start"), ("dataset", "done")]


class SlowToy(ToyOscillator):
    """The toy oscillator with a setting that changes only its speed (``sleep_s``) declared as such."""

    identity_ignores = ("sleep_s",)


TWO_STAGES = SPEC.replace('"test_dataset_toy:ToyOscillator", n_frames: 10', '"test_core_runner:SlowToy", n_frames: 10, sleep_s: 0.0').replace("n: 6", "n: 12").replace(
    "stages: [dataset]", "surrogate: {type: mlp, max_epochs: 2, hidden: [4, 4, 4], batch_size: 4}\n"
    "validator: {type: simulator, batch_size: 4}\nstages: [dataset, train]")


def test_settings_that_change_only_speed_keep_stages_cached(tmp_path):
    """A simulator's identity_ignores fields, the validator's batch size and dataset.batch_size say how fast
    work goes, not what it computes: changing them (a run moved to a GPU with bigger batches) keeps every
    stage cached; a setting that changes results still re-runs its stage."""
    out = tmp_path / "run"
    assert events_of(TWO_STAGES, out) == [("dataset", "start"), ("dataset", "done"), ("train", "start"), ("train", "done")]
    faster = (TWO_STAGES.replace("sleep_s: 0.0", "sleep_s: 0.001").replace("batch_size: 3", "batch_size: 2")
              .replace("validator: {type: simulator, batch_size: 4}",
                       "validator: {type: simulator, batch_size: 64, extract_workers: 2}"))
    assert events_of(faster, out) == [("dataset", "cached"), ("train", "cached")]
    other_training = faster.replace("max_epochs: 2", "max_epochs: 3")  # a setting that changes results
    assert events_of(other_training, out) == [("dataset", "cached"), ("train", "start"), ("train", "done")]


def test_run_directories_keyed_before_execution_settings_left_the_keys_stay_cached(tmp_path):
    """Stage markers written when keys still hashed the execution settings (before 2026-11-26) are
    recognised: upgrading invphys does not re-run finished stages."""
    from invphys import registry
    from invphys.pipeline import cache
    from invphys.pipeline.runner import stage_module

    out = tmp_path / "run"
    events_of(TWO_STAGES, out)
    spec, reg = parse_spec(TWO_STAGES), registry.default_registry()
    upstream: dict = {}
    for stage in ("dataset", "train"):  # rewrite both markers with the old key (execution settings in it)
        done_path = out / stage / "DONE.json"
        done = json.loads(done_path.read_text())
        sections = tuple(stage_module(stage).DEPENDS_ON)
        components = {"spec": cache.digest(cache.key_inputs(spec, sections, reg, execution=True)),
                      "plugins": done["components"]["plugins"], "data": done["components"]["data"],
                      "upstream": cache.digest(upstream)}
        done["fingerprint"] = cache.digest({"components": components, "stage": stage})
        assert done["fingerprint"] != json.loads(done_path.read_text())["fingerprint"]  # the keys do differ
        done_path.write_text(json.dumps(done))
        upstream[stage] = [done["fingerprint"], done["run_id"]]
    assert events_of(TWO_STAGES, out) == [("dataset", "cached"), ("train", "cached")]
    # an old marker whose inputs did change still re-runs
    assert events_of(TWO_STAGES.replace("n: 12", "n: 13"), out)[0] == ("dataset", "start")
