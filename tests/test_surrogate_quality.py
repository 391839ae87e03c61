"""The ensemble's measured-best defaults (SiLU, AdamW, one-cycle): NumPy export, old models, paper settings."""

from __future__ import annotations

import json

import numpy as np
import pytest
from models_data import smooth

from invphys.inverter import export
from invphys.inverter.numeric import Program
from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
from invphys.plugins.surrogates.mlp import MLPSurrogate

PAPER = dict(activation="relu", batch_norm=True, dropout=0.1, optimizer="adam", schedule="constant", lr=1e-3)


@pytest.fixture(scope="module")
def silu_ensemble():
    t, y = smooth(200, seed=0)
    ens = EnsembleSurrogate(members=3, hidden=(32, 32, 16), max_epochs=120, seed=0)
    ens.fit(t, y)
    return ens


def test_defaults_are_the_measured_ones_and_the_mlp_stays_the_papers() -> None:
    e, m = EnsembleSurrogate.Config(), MLPSurrogate.Config()
    assert (e.activation, e.batch_norm, e.dropout, e.optimizer, e.schedule) == ("silu", False, 0.0, "adamw",
                                                                                "one_cycle")
    assert (m.activation, m.batch_norm, m.dropout, m.optimizer, m.schedule, m.lr, m.patience) == \
        ("relu", True, 0.1, "adam", "constant", 1e-3, 50)


def test_silu_ensemble_learns_and_numpy_program_agrees(silu_ensemble, tmp_path) -> None:
    import torch

    ens = silu_ensemble
    assert isinstance(ens._net.members[0].b1[1], torch.nn.SiLU)
    assert ens.metrics["r2"] > 0.75
    prog = export.surrogate_program(ens, 9)
    assert prog is not None and prog.ops[0]["act"] == "silu"
    prog = Program.load(prog.save(tmp_path / "s.npz"))
    q = smooth(50, seed=5)[0]
    k = prog(q).astype(np.float64)
    mean, std = ens.predict_with_uncertainty(q)
    assert np.allclose(k.mean(0), mean, rtol=1e-4, atol=1e-5)
    assert np.allclose(k.std(0), std, rtol=1e-3, atol=1e-5)
    # the same weights through ReLU give other numbers: the activation really is applied
    relu = Program([{"op": "skip_mlp", "prefix": "s."}], prog.arrays)(q)
    assert not np.allclose(relu.mean(0), mean, atol=1e-3)


def test_silu_ensemble_save_load_round_trip(silu_ensemble, tmp_path) -> None:
    q = smooth(30, seed=6)[0]
    back = EnsembleSurrogate.load(silu_ensemble.save(tmp_path / "e"))
    assert back.config.activation == "silu"
    assert np.array_equal(back.predict(q), silu_ensemble.predict(q))


@pytest.mark.parametrize("cls", [MLPSurrogate, EnsembleSurrogate])
def test_models_saved_before_the_new_settings_load_as_paper_relu(cls, tmp_path) -> None:
    t, y = smooth(120, seed=1)
    extra = {"members": 2} if cls is EnsembleSurrogate else {}
    old = cls(hidden=(32, 32, 16), max_epochs=10, patience=5, seed=0, **PAPER, **extra)
    old.fit(t, y)
    d = old.save(tmp_path / "m")
    meta = json.loads((d / "model.json").read_text())
    for key in ("activation", "optimizer", "schedule"):  # what a model saved before these existed lacks
        del meta["config"][key]
    (d / "model.json").write_text(json.dumps(meta))
    back = cls.load(d)
    assert (back.config.activation, back.config.optimizer, back.config.schedule) == ("relu", "adam", "constant")
    q = smooth(20, seed=2)[0]
    assert np.array_equal(back.predict(q), old.predict(q))
    # and its NumPy program is the plain (ReLU) op an old bundle holds
    prog = export.surrogate_program(back, 9)
    assert prog is not None and "act" not in prog.ops[0]


def test_unknown_program_activation_is_refused() -> None:
    arrays = {f"s.{k}": np.zeros((1, 2, 2), np.float32) for k in ("w1", "b1", "w2", "b2", "wo", "bo")}
    arrays["s.w3"] = np.zeros((1, 4, 2), np.float32)
    with pytest.raises(ValueError, match="activation"):
        Program([{"op": "skip_mlp", "prefix": "s.", "act": "tanh"}], arrays)(np.zeros((1, 2)))


def test_members_early_stop_on_their_own_carves_and_report_out_of_fold() -> None:
    t, y = smooth(200, seed=3)
    ens = EnsembleSurrogate(members=3, hidden=(32, 32, 16), max_epochs=30, seed=4)
    m = ens.fit(t, y)
    assert m["validation"] == "out_of_fold"
    # three 10 % carves (seeds 4, 5, 6): the out-of-fold rows are their union, more than one carve's 20
    assert 20 < m["n_val"] <= 60 and m["n_train"] == 180
    assert len(m["member_r2"]) == 3 and m["r2"] > 0.3
    from invphys.models.data import r2_scores, split_indices

    va = split_indices(200, 0.1, 5)[1]  # member 2's carve: its member_r2 is measured there
    assert m["member_r2"][1] == pytest.approx(r2_scores(y[va], ens._member_predict(t[va])[1])[0])
    shared = EnsembleSurrogate(members=3, hidden=(32, 32, 16), max_epochs=30, seed=4, member_splits=False)
    assert shared.fit(t, y)["n_val"] == 20


def test_committed_bundle_surrogate_loads_with_its_saved_activation_and_matches_its_numpy_form() -> None:
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent / "inverters" / "orange_peel_quick"
    if not (root / "surrogate" / "model.json").is_file():
        pytest.skip("no committed orange_peel_quick bundle")
    saved = json.loads((root / "surrogate" / "model.json").read_text())["config"]
    model = EnsembleSurrogate.load(root / "surrogate")
    assert model.config.activation == saved.get("activation", "relu")
    prog = Program.load(root / "inference" / "surrogate.npz")
    x = np.random.default_rng(0).uniform(0, 1, (40, model.dims[0]))
    ref = model.predict(x)
    assert np.allclose(prog(x).mean(0), ref, rtol=1e-4, atol=1e-5 * np.abs(ref).max())
