"""VAE and RealNVP latent models on real orange-peel data: learning, round trips, persistence, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from models_data import orange_split, smooth
from pydantic import ValidationError

from invphys.core.interfaces import LatentModel
from invphys.models.data import ModelLoadError, NotFittedError, TrainingDataError
from invphys.plugins.latents.realnvp import RealNVPLatent
from invphys.plugins.latents.vae import VAELatent

CLASSES = (VAELatent, RealNVPLatent)


@pytest.fixture(scope="module")
def orange():
    return orange_split(seed=0)


@pytest.fixture(scope="module", params=CLASSES, ids=lambda c: c.name)
def fitted(request, orange):
    tt, yt, tv, yv = orange
    model = request.param(max_epochs=70, warmup_epochs=20, patience=20, seed=2)
    model.fit(tt, yt, validation=(tv, yv))
    return model


def test_training_lowers_the_loss_and_the_head_predicts_features(fitted) -> None:
    hist = fitted.history
    assert min(hist["val_loss"]) < 0.4 * hist["val_loss"][0]
    parts = hist["parts"]
    assert parts["recon"][-1] < parts["recon"][0] and parts["pred"][-1] < 0.5 * parts["pred"][0]
    assert fitted.metrics["head_r2"] > 0.6, fitted.metrics["head_r2_per_feature"]
    assert isinstance(fitted, LatentModel) and fitted.latent_dim == 4


def test_decode_encode_round_trip_error_is_bounded(fitted, orange) -> None:
    _, _, tv, _ = orange
    z = fitted.encode(tv)
    assert z.shape == (len(tv), 4) and np.isfinite(z).all()
    rec = fitted.decode(z)
    assert rec.shape == tv.shape and rec.min() >= 0.0 and rec.max() <= 1.0
    mse = float(((rec - tv) ** 2).mean())
    # 9 independent uniform parameters through a 4-D code: predicting the mean scores 1/12 = 0.083
    assert mse < 0.065, mse
    assert mse == pytest.approx(fitted.metrics["recon_mse"])
    # codes of the data sit in the optimisers' box [-3, 3]^4
    assert (np.abs(z) <= fitted.latent_bound).all(axis=1).mean() > 0.95
    # decode clips: codes far outside still give valid parameters
    far = fitted.decode(np.full((3, 4), 50.0))
    assert far.min() >= 0.0 and far.max() <= 1.0


def test_save_load_gives_identical_outputs(fitted, orange, tmp_path) -> None:
    _, _, tv, _ = orange
    fitted.save(tmp_path / "m")
    back = type(fitted).load(tmp_path / "m")
    z = fitted.encode(tv)
    assert np.array_equal(back.encode(tv), z)
    assert np.array_equal(back.decode(z), fitted.decode(z))
    assert np.array_equal(back.predict_features(z), fitted.predict_features(z))
    meta = json.loads((tmp_path / "m" / "model.json").read_text())
    assert meta["kind"] == "latent_model" and meta["data_fingerprint"] == fitted.data_fingerprint
    other = RealNVPLatent if isinstance(fitted, VAELatent) else VAELatent
    with pytest.raises(ModelLoadError):
        other.load(tmp_path / "m")


def test_flow_is_bijective_on_its_latent_space(orange) -> None:
    import torch

    model = RealNVPLatent(max_epochs=3, warmup_epochs=1, seed=0)
    model.fit(*orange[:2])
    net = model._net
    with torch.no_grad():
        h = net.proj_in(torch.as_tensor(orange[2], dtype=torch.float32))
        z, ladj = net.flow_forward(h)
        z_ref, ladj_ref = net.zuko_forward(h)  # zuko's own evaluation of the same couplings
        assert torch.allclose(z, z_ref, atol=1e-6) and torch.allclose(ladj, ladj_ref, atol=1e-5)
        assert torch.allclose(net.flow_inverse(z), h, atol=1e-5)
        assert torch.allclose(net.flow().inv(z), h, atol=1e-5)
        # 6 couplings, each scaling 2 of 4 coordinates by at most e^(+-1): |log det| <= 12
        assert ladj.abs().max() <= 12.0 + 1e-5
    assert len(net.flow.transforms) == 6


def test_same_seed_same_model_and_warmup_is_linear() -> None:
    t, y = smooth(80, seed=5)
    a, b = (VAELatent(max_epochs=6, warmup_epochs=4, encoder_hidden=(32, 16), decoder_hidden=(16, 32), seed=3)
            for _ in range(2))
    a.fit(t, y)
    b.fit(t, y)
    assert np.array_equal(a.encode(t), b.encode(t))
    # validation loss uses the final beta throughout: the KL part is reported unweighted
    assert len(a.history["parts"]["kl"]) == 6


def test_bad_configs_and_inputs(fitted) -> None:
    with pytest.raises(ValidationError, match="beta"):
        VAELatent(beta=-1)
    with pytest.raises(ValidationError, match="scale_bound"):
        RealNVPLatent(scale_bound=0)
    with pytest.raises(ValidationError, match="latent_dim"):
        RealNVPLatent(latent_dim=1)
    with pytest.raises(NotFittedError):
        VAELatent().encode(np.zeros((1, 9)))
    with pytest.raises(TrainingDataError, match=r"\(B, 4\)"):
        fitted.decode(np.zeros((2, 3)))


def test_conformance_check_passes(fitted, orange) -> None:
    from invphys.testing import check_latent_model

    mse = check_latent_model(fitted, orange[2])
    assert mse == pytest.approx(fitted.metrics["recon_mse"])


def test_fitted_models_pickle(fitted, orange) -> None:
    import pickle

    back = pickle.loads(pickle.dumps(fitted))  # e.g. to ship to Ray or process-pool workers
    z = fitted.encode(orange[2][:5])
    assert np.array_equal(back.encode(orange[2][:5]), z) and np.array_equal(back.decode(z), fitted.decode(z))
