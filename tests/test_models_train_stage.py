"""The train stage end to end: a real (toy) simulator dataset -> trained, saved, reloadable models."""

from __future__ import annotations

import json

import numpy as np
import pytest
from models_data import orange_tiny

from invphys.core.errors import SpecError

SPEC = """\
name: train-stage-test
seed: 2
stages: [dataset, train]
simulator: {type: "test_dataset_toy:ToyOscillator", substeps: 1}
dataset: {n: 96, batch_size: 32, sampler: sobol}
surrogate: {type: mlp, max_epochs: 40, patience: 10, hidden: [64, 64, 32]}
latent_models:
  flow: {type: realnvp, latent_dim: 2, max_epochs: 25, warmup_epochs: 5, n_couplings: 2}
  vae: {type: vae, latent_dim: 2, max_epochs: 25, warmup_epochs: 5}
"""


def test_train_stage_trains_saves_and_is_cached(tmp_path) -> None:
    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import StageContext, run_spec
    from invphys.plugins.latents.realnvp import RealNVPLatent
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    spec = parse_spec(SPEC)
    out = tmp_path / "run"
    summaries = run_spec(spec, out, progress=False)
    s = summaries["train"]
    train_dir = out / "train"
    n_ok = summaries["dataset"]["ok"]
    assert s["n_train"] + s["n_test"] == n_ok and s["n_test"] == max(1, round(n_ok * 0.2))
    assert np.isfinite(s["surrogate"]["r2"]) and s["surrogate"]["r2"] > 0.3
    assert set(s["surrogate"]["r2_per_feature"]) == set(s["feature_names"])
    assert set(s["latent_models"]) == {"flow", "vae"}
    for name in ("metrics.json", "metrics.md", "curves_surrogate.png", "parity_surrogate.png",
                 "curves_latent_flow.png", "curves_latent_vae.png"):
        assert (train_dir / name).stat().st_size > 100, name
    assert "| flow | realnvp | 2 |" in (train_dir / "metrics.md").read_text()
    assert json.loads((train_dir / "metrics.json").read_text())["n_test"] == s["n_test"]

    # what later stages load through the runner context is what was trained, on the right data
    ctx = StageContext(spec=spec, out=out, stage="invert", registry=__import__("invphys").registry.default_registry(),
                       console=None, progress=False)
    sur, flow = ctx.surrogate(), ctx.latent("flow")
    assert isinstance(sur, MLPSurrogate) and isinstance(flow, RealNVPLatent)
    data = ctx.dataset()
    _, test_idx = ctx.split()
    assert sur.info["dataset_fingerprint"] == data.fingerprint
    assert sur.info["feature_names"] == list(data.feature_names)
    from invphys.models.data import r2_scores

    assert r2_scores(data.y[test_idx], sur.predict(data.theta[test_idx]))[0] == pytest.approx(s["surrogate"]["r2"])
    assert flow.decode(flow.encode(data.theta[:5])).shape == (5, data.theta.shape[1])

    seen = []
    run_spec(spec, out, progress=False, on_stage=lambda stage, status, _: seen.append((stage, status)))
    assert seen == [("dataset", "cached"), ("train", "cached")]


def test_train_models_directly_on_the_orange_fixture(tmp_path) -> None:
    from invphys.pipeline.stages.train import train_models
    from invphys.registry import Registry

    d = orange_tiny()
    n = len(d["theta"])
    idx = np.random.default_rng(0).permutation(n)
    summary = train_models(d["theta"], d["y"], idx[: n - 100], idx[n - 100:],
                           surrogate={"type": "ensemble", "members": 2, "max_epochs": 30, "hidden": [64, 64, 32]},
                           latent_models={}, out=tmp_path, registry=Registry(autoload=False),
                           feature_names=list(d["feature_names"]), param_names=list(d["param_names"]))
    assert summary["surrogate"]["type"] == "ensemble" and summary["surrogate"]["mean_std"] > 0
    assert summary["surrogate"]["r2"] > 0.5
    assert (tmp_path / "surrogate" / "weights.pt").is_file()
    with pytest.raises(SpecError, match=r"surrogate\.dropout"):
        train_models(d["theta"], d["y"], idx[:400], idx[400:], surrogate={"type": "mlp", "dropout": 3},
                     latent_models={}, out=tmp_path / "bad", registry=Registry(autoload=False))


def test_spec_validation_locates_bad_model_settings() -> None:
    from invphys.core.spec import parse_spec

    bad = SPEC.replace("hidden: [64, 64, 32]", "hidden: [64, 0, 32], dropout: 2").replace(
        "latent_dim: 2, max_epochs: 25, warmup_epochs: 5, n_couplings: 2", "latent_dim: 1").replace(
        "vae: {type: vae,", "vae: {type: vae, betta: 1,")
    with pytest.raises(SpecError) as err:
        parse_spec(bad)
    text = str(err.value)
    for where in ("surrogate.hidden.1", "surrogate.dropout", "latent_models.flow.latent_dim",
                  "latent_models.vae.betta"):
        assert where in text, text
