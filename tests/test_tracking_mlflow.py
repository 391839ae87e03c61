"""``tracker: mlflow`` and ``tracker: none`` on a tiny real run; the tracker API on its own."""

from __future__ import annotations

import io

import pytest

SPEC = """
name: tracking-mlflow
seed: 2
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 48, batch_size: 48}
surrogate: {type: ensemble, members: 2, hidden: [8, 8, 8], max_epochs: 5, patience: 50}
stages: [dataset, train]
"""


def _run(tmp_path, tracker: str):
    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out = tmp_path / "run"
    summaries = run_spec(parse_spec(SPEC + f"tracker: {tracker}\n"), out, progress=False,
                         console=Console(file=io.StringIO()))
    return out, summaries


@pytest.mark.slow  # MLflow creates its SQLite schema (alembic migrations): ~10 s
def test_mlflow_run_holds_every_epoch_final_metrics_and_artifacts(tmp_path, monkeypatch) -> None:
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    out, summaries = _run(tmp_path, "{type: mlflow, experiment: tiny}")
    assert not (out / "tensorboard").exists()
    client = MlflowClient(tracking_uri=f"sqlite:///{out / 'mlflow.db'}")
    (run,) = client.search_runs([client.get_experiment_by_name("tiny").experiment_id])
    assert run.info.status == "FINISHED" and run.info.run_name == "tracking-mlflow"
    epochs = summaries["train"]["surrogate"]["metrics"]["epochs"]
    for k in (1, 2):  # each ensemble member's curve, one point per epoch
        history = client.get_metric_history(run.info.run_id, f"train/surrogate/member_{k}/val_loss")
        assert [m.step for m in history] == list(range(epochs[k - 1]))
    assert run.data.metrics["train/surrogate/r2"] == pytest.approx(summaries["train"]["surrogate"]["r2"])
    assert run.data.metrics["dataset/ok"] == summaries["dataset"]["ok"]
    stored = {f.path for f in client.list_artifacts(run.info.run_id, "train")}
    assert {"train/metrics.json", "train/metrics.md", "train/summary.json"} <= stored
    assert (out / "mlartifacts").is_dir()  # artifacts stay inside the run directory
    # the spec's settings as params, so that runs compare by them (issue 50: there were none)
    params = run.data.params
    assert params["dataset.n"] == "48" and params["surrogate.type"] == "ensemble"
    assert params["surrogate.hidden"] == "[8, 8, 8]" and params["tracker.experiment"] == "tiny"
    assert params["name"] == "tracking-mlflow" and params["dataset.path"] == "null"


def test_mlflow_params_are_cut_to_its_limits_and_sent_in_batches(tmp_path, monkeypatch) -> None:
    pytest.importorskip("mlflow")
    from invphys.tracking.mlflow_tracker import MAX_PARAM_VALUE, MLflowTracker

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    tracker = MLflowTracker(tmp_path, experiment="limits")
    tracker.log_params({**{f"k{i}": i for i in range(150)}, "long": "x" * 10_000, "odd key!": True})
    tracker.close()
    params = tracker.run.data.params
    assert len(params) == 152 and params["k149"] == "149" and params["odd key_"] == "true"
    assert len(params["long"]) == MAX_PARAM_VALUE and params["long"].endswith("...")


def test_tracker_none_writes_nothing(tmp_path) -> None:
    out, _ = _run(tmp_path, "none")
    assert (out / "train" / "metrics.json").is_file()
    assert not (out / "tensorboard").exists() and not (out / "mlflow.db").exists()


def test_create_tracker_and_scopes(tmp_path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from invphys.core.errors import InvphysError
    from invphys.tracking import NullTracker, create_tracker

    assert isinstance(create_tracker("none", tmp_path), NullTracker)
    with pytest.raises(InvphysError, match="Did you mean 'mlflow'"):
        create_tracker("mlflo", tmp_path)
    with create_tracker(None, tmp_path) as tracker:  # the default: TensorBoard under the run directory
        tracker.scoped("a").scoped("b").log_scalars({"x": 1.5, "nested": {"y": 2}, "skip": [1], "text": "t",
                                                     "inf": float("inf"), "flag": True}, step=3)
    acc = EventAccumulator(str(tmp_path / "tensorboard"))
    acc.Reload()
    assert sorted(acc.Tags()["scalars"]) == ["a/b/nested/y", "a/b/x"]
    assert [(e.step, e.value) for e in acc.Scalars("a/b/x")] == [(3, 1.5)]
