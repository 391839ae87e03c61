"""bench_surrogate_ceiling: the ceiling is the recovery of the features predicted at the TRUE parameters (a
perfect surrogate scores 1, one queried elsewhere does not), the power law finds the rows to a goal, and the
script runs end to end on a tiny real bundle (nested sizes, an extra store, one JSON of the documented shape;
variant settings, a plot; bad input is one error line and exit 2)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import benchmark_modules
import numpy as np
import pytest

from invphys.core.objectives import recovery_reward


def _bench():
    return benchmark_modules.load("bench_surrogate_ceiling")


@pytest.fixture(scope="module", name="run")
def toy_run(tmp_path_factory) -> Path:
    """A toy-oscillator run (dataset + train stages): its inverter bundle and dataset store."""
    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    spec = {"name": "ceiling-toy", "description": "tiny bundle for the ceiling benchmark", "seed": 1,
            "simulator": {"type": "test_dataset_toy:ToyOscillator"}, "dataset": {"n": 120, "batch_size": 40},
            "surrogate": {"type": "ensemble", "members": 2, "hidden": [16, 16, 8], "max_epochs": 5},
            "stages": ["dataset", "train"]}
    out = tmp_path_factory.mktemp("ceiling") / "run"
    run_spec(validate_spec(spec), out, progress=False, console=Console(file=io.StringIO()))
    return out


def test_ceiling_is_recovery_at_the_true_parameters() -> None:
    bench = _bench()
    rng = np.random.default_rng(0)
    theta = rng.random((50, 3))
    w = rng.normal(size=(3, 4))
    y = np.sin(theta @ w)
    scales = np.array([0.5, 0.2, 1.0, 0.3])

    def truth(t: np.ndarray) -> np.ndarray:  # a perfect surrogate
        return np.sin(t @ w)

    np.testing.assert_allclose(bench.ceiling_rows(truth, theta, y, scales, 3.0), 1.0)
    # the same perfect surrogate asked at other parameters is no ceiling: R falls, as recovery_reward says
    shifted = bench.ceiling_rows(lambda t: truth(t[::-1]), theta, y, scales, 3.0)
    assert shifted.mean() < 0.9
    np.testing.assert_allclose(shifted, recovery_reward(truth(theta[::-1]), y, scales, 3.0))
    # kappa and scales are the given ones
    noisy = lambda t: truth(t) + 0.05  # noqa: E731
    np.testing.assert_allclose(bench.ceiling_rows(noisy, theta, y, scales, 2.0),
                               np.exp(-2.0 * np.sqrt(np.mean((0.05 / scales) ** 2))))
    s = bench.score_set(truth(theta), theta, y, scales, 3.0, list("abcd"), 50, 0)
    assert s["ceiling"] == pytest.approx(1.0) and s["ceiling_ci95"] == pytest.approx([1.0, 1.0])
    assert s["r2_mean"] == pytest.approx(1.0) and list(s["r2_per_feature"]) == list("abcd")


def test_power_law_finds_the_rows_to_a_goal() -> None:
    bench = _bench()
    ns = [1000, 2000, 4000, 8000]
    cs = [1 - 2.0 * n**-0.25 for n in ns]
    fit = bench.power_law(ns, cs, 0.92)
    assert fit["a"] == pytest.approx(2.0) and fit["b"] == pytest.approx(0.25)
    assert fit["rows_to_goal"] == pytest.approx((2.0 / 0.08) ** 4, rel=1e-6)
    assert bench.power_law(ns, [0.8, 0.8, 0.79, 0.79], 0.92)["rows_to_goal"] is None  # flat or falling: never
    assert bench.power_law([1000], [0.8], 0.92) is None
    # the fitted rows and their bootstrap interval from per-target R (the last three sizes fitted apart)
    rng = np.random.default_rng(1)
    curve = [(n, {"s": np.clip(c + rng.normal(0, 0.01, 400), 0, 1)}) for n, c in zip(ns, cs, strict=True)]
    f = bench.fits(curve, {"s": 0.92}, 200, 0)["s"]
    assert f["all"]["rows_to_goal_ci95"][0] < (2.0 / 0.08) ** 4 < f["all"]["rows_to_goal_ci95"][1]
    assert f["last3"]["points"] == 3 and f["all"]["points"] == 4


def test_end_to_end_on_a_tiny_bundle(run: Path, tmp_path: Path) -> None:
    from invphys.core.dataset import DatasetStore
    from invphys.inverter.bundle import Bundle

    bench = _bench()
    bundle, store = run / "inverter", run / "dataset" / "store"
    out = tmp_path / "r" / "ceiling.json"
    rc = bench.main(["--bundle", str(bundle), "--sets", "test=@test", f"toy={store}", "--sizes", "80", "40",
                     "--extra-train", str(store), str(store), "--members", "2", "--max-epochs", "4", "--small-below", "50",
                     "--small-max-epochs", "2", "--goal", "toy=0.99", "--bootstrap", "30", "--out", str(out),
                     "--variant", "narrow={hidden: [8, 8, 4], max_epochs: 3}", "--plot", str(tmp_path / "c.png")])
    assert rc == 0
    rec = json.loads(out.read_text())
    b = Bundle(bundle)
    n_train = len(b.data("train")[0])
    n_store = len(DatasetStore(store).arrays(ok_only=True).theta)
    assert rec["benchmark"] == "surrogate_ceiling" and rec["device"].startswith("cpu")
    assert rec["command"].startswith("python ") and rec["git_commit"]
    assert rec["kappa"] == b.kappa and rec["train_rows"] == n_train and rec["extra_rows"] == 2 * n_store  # both stores joined
    assert [p["label"] for p in rec["points"]] == ["n=40", "n=80", f"n={n_train}+extra", f"n={n_train}:narrow"]
    assert [p["rows"] for p in rec["points"]] == [40, 80, n_train + 2 * n_store, n_train]
    assert [p["max_epochs"] for p in rec["points"]] == [2, 4, 4, 3] and {p["members"] for p in rec["points"]} == {2}
    assert rec["points"][-1]["settings_changed"] == {"hidden": [8, 8, 4], "max_epochs": 3}
    assert (tmp_path / "c.png").stat().st_size > 1000
    for p in rec["points"]:
        assert set(p["sets"]) == {"test", "toy"}
        for s in p["sets"].values():
            assert 0 <= s["ceiling_ci95"][0] <= s["ceiling"] <= s["ceiling_ci95"][1] <= 1
            assert len(s["r2_per_feature"]) == len(b.feature_names)
            assert sum(s["error_share"].values()) == pytest.approx(1.0)
    assert set(rec["power_law"]) == {"test", "toy"} and rec["power_law"]["toy"]["all"]["goal"] == 0.99
    assert len(rec["power_law"]["toy"]["last3"]["rows_to_goal_ci95"]) == 2
    # the shipped surrogate's ceiling on the held-out rows: its features at their true parameters
    theta, y = b.data("test")
    want = recovery_reward(b.surrogate.predict(theta), y, b.scales, b.kappa).mean()
    assert rec["shipped"]["test"]["ceiling"] == pytest.approx(want)
    assert rec["sets"]["test"] == {"store": "@test", "n": len(y)}


@pytest.mark.parametrize("args", [["--sizes", "100000"], ["--sizes", "40", "--sets", "nameonly"],
                                  ["--sizes", "40", "--sets", "x=/no/such/store"],
                                  ["--sizes", "40", "--variant", "v=[1, 2]"]])
def test_bad_input_is_one_error_line(run: Path, tmp_path: Path, capsys, args: list[str]) -> None:
    bench = _bench()
    argv = ["--bundle", str(run / "inverter"), "--sets", "test=@test", "--out", str(tmp_path / "o.json"), *args]
    assert bench.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")


def test_variants_train_on_the_extra_rows_when_asked() -> None:
    """--variants-on-extra: a variant point joins the --extra-train rows (capacity measured at the larger size);
    without it (or without extra stores) a variant trains on the bundle's rows alone."""
    import argparse

    bench = _bench()
    base = dict(sizes=[40], small_below=0, small_members=None, small_max_epochs=None, members=None, max_epochs=None,
                variant=["wide={hidden: [8, 8]}"])
    on = bench.plan(argparse.Namespace(**base, extra_train=["s"], variants_on_extra=True), 100)
    off = bench.plan(argparse.Namespace(**base, extra_train=["s"], variants_on_extra=False), 100)
    none = bench.plan(argparse.Namespace(**base, extra_train=None, variants_on_extra=True), 100)
    assert (on[-1]["label"], on[-1]["extra"]) == ("n=100+extra:wide", True)
    assert (off[-1]["label"], off[-1]["extra"]) == ("n=100:wide", False)
    assert (none[-1]["label"], none[-1]["extra"]) == ("n=100:wide", False)
