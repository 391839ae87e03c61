"""The stage runner: caching by fingerprint, re-running what changed, and the dataset fallback."""

from __future__ import annotations

import json

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

    from invphys.core.generate import generate_dataset

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
