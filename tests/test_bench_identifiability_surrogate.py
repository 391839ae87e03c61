"""bench_identifiability --surrogate: the shipped quick bundle's fitted ensemble, differentiated at the
simulator mode's base points and stencil, gives full-rank 12 x 9 Jacobians through the same statistics
code, and that code reports two identical parameter columns as rank-deficient."""

from __future__ import annotations

import json
from pathlib import Path

import benchmark_modules
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
BUNDLE = ROOT / "inverters" / "orange_peel_quick"
DATASET = ROOT / "datasets" / "orange_peel_quick"
POINTS = 6

pytestmark = pytest.mark.skipif(not (BUNDLE / "manifest.yaml").is_file() or not DATASET.is_dir(),
                                reason="the shipped quick bundle or dataset is not in this checkout")


def _bench():
    return benchmark_modules.load("bench_identifiability")


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[object, dict, Path]:
    bench = _bench()
    out = tmp_path_factory.mktemp("ident") / "ident.json"
    res = bench.main(["--surrogate", str(BUNDLE), "--scales-from", str(DATASET), "--points", str(POINTS),
                      "--out", str(out)])
    return bench, res, out


def test_surrogate_mode_runs_and_records_its_provenance(run) -> None:
    _, res, out = run
    saved = json.loads(out.read_text())
    assert saved == json.loads(json.dumps(res))
    assert saved["mode"] == "surrogate"
    assert saved["bundle"] == str(BUNDLE)
    assert (saved["simulator"], saved["simulator_version"], saved["preset"]) == ("orange_peel", "0.3.0", "quick")
    assert saved["dataset"]["path"] == str(DATASET) and saved["dataset"]["version"] == "0.3.0"
    assert saved["scales_from"] == str(DATASET)
    assert saved["device"] == "cpu" and saved["machine"]["cpu"]
    assert "--surrogate" in saved["command"] and saved["date"].endswith("Z")
    assert saved["evaluations"] == POINTS * (1 + 2 * 9) and saved["failed"] == 0
    assert saved["surrogate_test_r2"]["overall"] > 0.5


def test_jacobians_are_full_rank_and_every_parameter_moves_the_features(run) -> None:
    _, res, _ = run
    J = np.asarray(res["jacobians"])
    assert J.shape == (POINTS, 12, 9)
    assert res["points_used"] == POINTS
    assert res["numerical_rank_1e-3"][9] == POINTS            # rank 9 at 1e-3 at every base point
    assert sum(res["numerical_rank_1e-3"]) == POINTS
    assert all(v > 0 for v in res["sensitivity_min_over_points"].values())
    assert all(v > 0 for v in res["sensitivity_median"].values())
    assert max(res["max_abs_cosine_median"].values()) < 0.99


def test_jacobian_is_the_bundle_surrogates_central_difference(run) -> None:
    """Column j of the first point's J = (f(b + h e_j) - f(b - h e_j)) / (2 h s), via the public API."""
    import invphys

    bench, res, _ = run
    h = res["step"]
    b = bench.base_points(POINTS, 9, h, res["seed"])[0]
    predict = invphys.load_inverter(BUNDLE).bundle.surrogate.predict
    scales = np.asarray(res["scales"])
    for j in (0, 4, 8):
        e = np.zeros(9)
        e[j] = h
        col = (predict(b + e)[0] - predict(b - e)[0]) / (2 * h) / scales
        np.testing.assert_allclose(np.asarray(res["jacobians"][0])[:, j], col, atol=2e-5)


def test_statistics_report_identical_columns_as_rank_deficient(run) -> None:
    bench, res, _ = run
    names = tuple(res["param_names"])
    # a hand-built, well-conditioned Jacobian whose rho column is made equal to E's
    q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(12, 9)))
    J = q * np.linspace(2.0, 0.5, 9)
    J[:, 1] = J[:, 0]
    stats = bench.summarise([J, 1.5 * J], names)
    assert stats["most_alike_pair"][:2] == ["E", "rho"] and stats["most_alike_pair"][2] == 1.0
    assert stats["max_abs_cosine_median"]["E"] == 1.0
    assert stats["numerical_rank_1e-3"][8] == 2 and stats["numerical_rank_1e-3"][9] == 0
    assert stats["numerical_rank_1e-2"][8] == 2
    # the same on the surrogate's own Jacobians: two equal columns can never be rank 9
    Js = [np.array(Jk) for Jk in res["jacobians"]]
    for Jk in Js:
        Jk[:, 7] = Jk[:, 3]
    stats = bench.summarise(Js, names)
    assert stats["max_abs_cosine_median"]["eta_s"] == 1.0
    assert stats["numerical_rank_1e-3"][9] == 0
    assert stats["numerical_rank_1e-3"][8] == POINTS
