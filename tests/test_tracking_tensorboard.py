"""A quick-start-shaped run on tiny data writes TensorBoard events for every training step; read back."""

from __future__ import annotations

import io
import json

import pytest

SPEC = """
name: tracking-quickstart
seed: 5
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 64, batch_size: 32}
surrogate: {type: mlp, hidden: [16, 16, 8], max_epochs: 12, patience: 50}
latent_models:
  flow: {type: realnvp, latent_dim: 2, max_epochs: 6, warmup_epochs: 2, n_couplings: 2}
optimizers:
  ppo: {type: ppo, total_timesteps: 128, n_steps: 16, n_envs: 4, horizon: 4, net_arch: [8]}
  gc: {type: gc_ppo, total_timesteps: 128, n_steps: 16, n_envs: 4, horizon: 4, net_arch: [8]}
objectives:
  lively: {weights: {peak_abs: 1.0}}
targets: {n: 2, validate: 0}
stages: [dataset, train, invert]
"""


@pytest.fixture(scope="module")
def events(tmp_path_factory):
    from rich.console import Console
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    out = tmp_path_factory.mktemp("run")
    summaries = run_spec(parse_spec(SPEC), out, progress=False, console=Console(file=io.StringIO()))
    logdir = out / "tensorboard"
    assert list(logdir.glob("events.out.tfevents.*")), "no event file in OUT/tensorboard"
    acc = EventAccumulator(str(logdir), size_guidance={"scalars": 0, "tensors": 0})
    acc.Reload()
    return out, summaries, acc


def _series(acc, tag: str) -> list[tuple[int, float]]:
    return [(e.step, e.value) for e in acc.Scalars(tag)]


def test_every_epoch_of_every_model_is_an_event(events) -> None:
    out, _, acc = events
    for tag_prefix, saved in (("train/surrogate", out / "train" / "surrogate"),
                              ("train/latent_models/flow", out / "train" / "latent" / "flow")):
        history = json.loads((saved / "history.json").read_text())
        for curve in ("train_loss", "val_loss"):
            got = _series(acc, f"{tag_prefix}/{curve}")
            assert [s for s, _ in got] == list(range(history["epochs"])), curve
            assert [v for _, v in got] == pytest.approx(history[curve], rel=1e-5)
    # the flow's loss parts, per epoch too
    parts = json.loads((out / "train" / "latent" / "flow" / "history.json").read_text())["parts"]
    assert [v for _, v in _series(acc, "train/latent_models/flow/val_nll")] == pytest.approx(parts["nll"], rel=1e-5)


def test_ppo_learning_curves_come_through_sb3s_logger(events) -> None:
    _, summaries, acc = events
    tags = set(acc.Tags()["scalars"])
    rollout = 16 * 4
    # goal-conditioned: one policy, two updates of n_steps * n_envs = 64 steps
    steps = [s for s, _ in _series(acc, "invert/policy/gc/rollout/ep_rew_mean")]
    assert steps == [rollout, 2 * rollout]
    assert "invert/policy/gc/train/value_loss" in tags and "invert/policy/gc/train_recovery" in tags
    # per-objective PPO: one policy per named objective
    assert [s for s, _ in _series(acc, "invert/ppo/lively/rollout/ep_rew_mean")] == [rollout, 2 * rollout]
    assert summaries["invert"]["prepare"]["gc"]["timesteps"] == 2 * rollout


def test_final_metrics_and_artifacts_of_each_stage(events) -> None:
    out, summaries, acc = events
    assert _series(acc, "train/surrogate/r2") == [(0, pytest.approx(summaries["train"]["surrogate"]["r2"], rel=1e-5))]
    assert _series(acc, "dataset/ok")[0][1] == summaries["dataset"]["ok"]
    assert "invert/optimizers/gc/target/mean_r_surrogate" in acc.Tags()["scalars"]
    from tensorboard.util import tensor_util

    text = tensor_util.make_ndarray(acc.Tensors("artifacts")[-1].tensor_proto).item().decode()
    for name in ("train/metrics.json", "invert/results.csv", "dataset/summary.json"):
        assert f"`{name}`" in text and str(out / name) in text


def test_a_run_on_a_stored_dataset_writes_events(tmp_path) -> None:
    """The quick start's shape: a dataset stage that reads a stored dataset (``dataset.path``), an MLP, a
    RealNVP flow and a goal-conditioned PPO policy in the flow's latent space, shrunk to a few epochs/steps."""
    from rich.console import Console
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from invphys.core.spec import validate_spec
    from invphys.data.generate import generate_dataset
    from invphys.pipeline.runner import run_spec

    simulator = {"type": "test_dataset_toy:ToyOscillator", "substeps": 8}
    store = tmp_path / "stored"
    generate_dataset(store, simulator, n=48, batch_size=16, seed=3, progress=False)
    data = {"name": "stored-quickstart", "seed": 0, "stages": ["dataset", "train", "invert"],
            "simulator": simulator, "dataset": {"path": str(store), "test_fraction": 0.2},
            "surrogate": {"type": "mlp", "hidden": [16, 16, 8], "max_epochs": 3},
            "latent_models": {"flow": {"type": "realnvp", "latent_dim": 2, "n_couplings": 2, "max_epochs": 2}},
            "optimizers": {"gc_ppo_flow": {"type": "gc_ppo", "space": "flow", "total_timesteps": 64, "n_envs": 8,
                                           "n_steps": 8, "net_arch": [8]}},
            "targets": {"n": 1, "validate": 0}}
    out = tmp_path / "run"
    summaries = run_spec(validate_spec(data), out, progress=False, console=Console(file=io.StringIO()))
    assert summaries["dataset"]["generated"] is False  # the stored rows were read, none simulated
    acc = EventAccumulator(str(out / "tensorboard"), size_guidance={"scalars": 0})
    acc.Reload()
    assert [e.step for e in acc.Scalars("train/surrogate/val_loss")] == [0, 1, 2]
    assert [e.step for e in acc.Scalars("train/latent_models/flow/val_loss")] == [0, 1]
    assert [e.step for e in acc.Scalars("invert/policy/gc_ppo_flow/rollout/ep_rew_mean")] == [64]


def test_the_spec_is_logged_as_hparams_and_figures_as_images(tmp_path) -> None:
    """Issue 50: TensorBoard had no hparams and no figures. A run logs its spec's settings (flattened keys)
    through the hparams plugin, and a stage's PNG figures as image summaries."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    from invphys.pipeline.runner import _track_stage
    from invphys.tracking import create_tracker

    stage = tmp_path / "report"
    (stage / "renders").mkdir(parents=True)
    for path in (stage / "recovery.png", stage / "renders" / "t00.png"):
        plt.figure(figsize=(2, 1.5), dpi=50)
        plt.plot([0, 1])
        plt.savefig(path)
        plt.close()
    with create_tracker("tensorboard", tmp_path) as tracker:
        tracker.log_params({"name": "x", "dataset.n": 64, "surrogate.hidden": "[16, 8]", "report.render": True,
                            "dataset.path": None})
        _track_stage(tracker, "report", stage, {"n": 1})
    acc = EventAccumulator(str(tmp_path / "tensorboard"), size_guidance={"images": 0, "tensors": 0})
    acc.Reload()
    assert acc.Tags()["images"] == ["report/recovery", "report/renders/t00"]
    image = acc.Images("report/recovery")[0]
    assert (image.width, image.height) == (100, 75) and image.encoded_image_string == (stage / "recovery.png").read_bytes()
    content = acc.PluginTagToContent("hparams")["_hparams_/session_start_info"]
    hparams = plugin_data_pb2.HParamsPluginData.FromString(content).session_start_info.hparams
    assert hparams["dataset.n"].number_value == 64 and hparams["surrogate.hidden"].string_value == "[16, 8]"
    assert hparams["report.render"].bool_value is True and hparams["dataset.path"].string_value == "null"


def test_spec_params_are_flat_section_keys() -> None:
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import spec_params

    params = spec_params(parse_spec(SPEC))
    assert params["surrogate.type"] == "mlp" and params["surrogate.hidden"] == "[16, 16, 8]"
    assert params["optimizers.gc.type"] == "gc_ppo" and params["objectives.lively.weights.peak_abs"] == 1.0
    assert params["dataset.n"] == 64 and params["seed"] == 5 and "description" not in params
