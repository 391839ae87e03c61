"""bench_simulator_surrogate --transform: the transforms round-trip, R^2 is scored in the transformed units
(with a raw-units copy), and without --transform the benchmark trains and scores exactly as before; --train-store
and --extra take rows of the same kind of runs only."""

from __future__ import annotations

import json
from pathlib import Path

import benchmark_modules
import numpy as np
import pytest

from invphys.core.dataset import DatasetStore, Row, RunIdentity, row_key
from invphys.core.results import RunStats, SimulationResult
from invphys.models.data import r2_scores

ROOT = Path(__file__).resolve().parent.parent
IDENT = RunIdentity("toy_oscillator", "tiny", "numpy", "1")


def _bench():
    return benchmark_modules.load("bench_simulator_surrogate")


def _store(path: Path, n: int = 40, ident: RunIdentity = IDENT, seed: int = 3) -> DatasetStore:
    """A tiny store: 2 parameters, a heavy-tailed positive feature above 0.02 and a smooth one."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        theta = rng.random(2)
        f = np.array([0.02 + 0.01 * np.exp(3 * theta[0] * theta[1]), theta[0] - theta[1]])
        stats = RunStats(substeps=1, wall_time_s=0.0, backend="numpy", device="cpu", preset="tiny",
                         simulator="toy_oscillator", simulator_version="1")
        res = SimulationResult(params=theta, ok=True, stats=stats, features=f)
        rows.append(Row(key=row_key(theta, ident), sample_index=i, theta=theta, params=theta, result=res))
    store = DatasetStore(path)
    with store.writer():
        store.create_or_check({"identity": ident.to_dict(), "param_names": ["a", "b"],
                               "feature_names": ["sep", "other"]})
        store.append(rows)
    return store


def test_transforms_round_trip_and_refuse_values_below_the_offset() -> None:
    bench = _bench()
    names = ["sep", "other"]
    v = np.array([0.021, 0.03, 0.138])
    _, log = bench.parse_transform("sep=log10", names, None)
    np.testing.assert_allclose(bench.forward(v, log), np.log10(v))
    _, gain = bench.parse_transform("sep=log10_gain:0.02", names, None)
    assert gain["offset"] == 0.02 and gain["kind"] == "log10_gain"
    np.testing.assert_allclose(bench.forward(v, gain), np.log10(v - 0.02))
    for rec in (log, gain):
        np.testing.assert_allclose(bench.inverse(bench.forward(v, rec), rec), v, rtol=1e-12)
    with pytest.raises(SystemExit):
        bench.forward(np.array([0.019, 0.03]), gain)
    for bad in ("sep=rank", "nope=log10", "sep", "sep=log10_gain"):  # no default baseline outside orange_peel
        with pytest.raises(SystemExit):
            bench.parse_transform(bad, names, None)


def test_orange_peel_default_baseline_is_the_unsettled_scene_separation() -> None:
    bench = _bench()
    _, rec = bench.parse_transform("final_separation=log10_gain", ["final_separation"],
                                   {"simulator": "orange_peel", "preset": "tiny"})
    # hemisphere of radius R: thin dome centroid at R/2, solid at 3R/8, so about R/8 = 0.019 m (R = 0.15 m)
    assert 0.01 < rec["offset"] < 0.03


def test_default_path_unchanged_and_transform_scored_in_both_units(tmp_path: Path) -> None:
    bench = _bench()
    store = _store(tmp_path / "s")
    base = bench.main([str(store.path), "--models", "mlp_new", "--curve", "40", "--out", str(tmp_path / "a.json")])
    saved = json.loads((tmp_path / "a.json").read_text())
    assert "transforms" not in saved and "r2_raw_units" not in saved["models"]["mlp_new"]
    # the default path is the plain pipeline: same split, same model, raw targets
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    data = store.arrays()
    perm = np.random.default_rng(0).permutation(len(data.theta))
    te, tr = np.sort(perm[:8]), np.sort(perm[8:])
    new = EnsembleSurrogate.Config().model_dump(include={"activation", "batch_norm", "dropout", "optimizer",
                                                         "schedule", "lr", "max_epochs", "patience"})
    model = MLPSurrogate(seed=0, val_fraction=0.1, **new)
    model.fit(data.theta[tr], data.y[tr])
    r2, per = r2_scores(data.y[te], model.predict(data.theta[te]))
    assert base["models"]["mlp_new"]["r2"] == pytest.approx(r2, abs=1e-9)
    assert list(base["models"]["mlp_new"]["r2_per_feature"].values()) == pytest.approx(per, abs=1e-9)

    out = bench.main([str(store.path), "--models", "mlp_new", "--curve", "40", "--transform", "sep=log10_gain:0.02",
                      "--out", str(tmp_path / "b.json")])
    assert out["transforms"]["sep"]["offset"] == 0.02
    res = out["models"]["mlp_new"]
    assert set(res["r2_per_feature_raw_units"]) == {"sep", "other"}
    assert np.isfinite([res["r2"], res["r2_raw_units"]]).all()
    assert json.loads((tmp_path / "b.json").read_text())["transforms"]["sep"]["kind"] == "log10_gain"


def test_train_store_of_another_preset_or_config_is_refused(tmp_path: Path) -> None:
    """Rows of another preset (or config hash, or version) never train a surrogate scored on the main store's runs;
    another backend of the same physics is accepted and trained on."""
    bench = _bench()
    main = _store(tmp_path / "main")
    for field, value in (("preset", "quick"), ("config", "0123456789abcdef"), ("version", "2")):
        other = _store(tmp_path / field, ident=RunIdentity(**{**IDENT.to_dict(), field: value}), seed=4)
        for flag in ("--train-store", "--extra"):
            with pytest.raises(SystemExit, match=f"not the same kind of runs.*{field} '{value}'"):
                bench.main([str(main.path), "--models", "mlp_new", flag, str(other.path),
                            "--out", str(tmp_path / "x.json")])
    assert not (tmp_path / "x.json").exists()
    warp = _store(tmp_path / "warp", ident=RunIdentity(**{**IDENT.to_dict(), "backend": "warp"}), seed=4)
    out = bench.main([str(main.path), "--models", "mlp_new", "--train-store", str(warp.path), "--test-all",
                      "--out", str(tmp_path / "w.json")])
    assert out["n_train"] == 40 and out["n_test"] == 40
