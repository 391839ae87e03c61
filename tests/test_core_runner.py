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
