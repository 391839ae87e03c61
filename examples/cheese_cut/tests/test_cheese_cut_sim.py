"""The cheese-cut plugin at its tiny preset on a CPU: conformance, physics of its features, errors.

Real simulator runs (960 particles, ~600 substeps each); Taichi compiles the engine's kernels once.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_cheese_cut.features import FEATURE_NAMES, CheeseCutFeatures
from invphys_cheese_cut.parameters import parameter_space
from invphys_cheese_cut.simulator import SERIES, CheeseCutSimulator

from invphys.core.errors import ParameterRangeError
from invphys.testing import (
    check_feature_extractor,
    check_plugin_class,
    check_render,
    check_simulator,
    check_trajectory_file,
)

SPACE = parameter_space()


@pytest.fixture(scope="module")
def sim() -> CheeseCutSimulator:
    return CheeseCutSimulator(preset="tiny", arch="cpu", batch_size=4)


@pytest.fixture(scope="module")
def sweep(sim) -> dict:
    """Centre parameters with E, rho and friction each set low and high: one batch of 6 runs."""
    base = SPACE.to_mapping(SPACE.center())
    rows = {f"{k}_{side}": {**base, k: v} for k, (lo, hi) in
            {"E": (3e4, 2e5), "rho": (0.95, 1.25), "friction": (0.0, 0.8)}.items()
            for side, v in (("lo", lo), ("hi", hi))}
    params = np.stack([SPACE.from_mapping(r) for r in rows.values()])
    results = sim.simulate(params)
    fe = CheeseCutFeatures()
    return {name: (res, fe.extract(res.trajectory)) for name, res in zip(rows, results, strict=True)}


def feat(sweep, row: str, name: str) -> float:
    return float(sweep[row][1][FEATURE_NAMES.index(name)])


def test_conformance(sim, sweep, tmp_path) -> None:
    check_plugin_class(CheeseCutSimulator)
    check_plugin_class(CheeseCutFeatures)
    results = check_simulator(sim, n_runs=2)
    y = check_feature_extractor(CheeseCutFeatures(), results)
    assert y.shape == (2, 13)
    traj = sweep["E_lo"][0].trajectory
    assert set(traj.series) == set(SERIES)
    check_trajectory_file(traj, tmp_path / "file")
    done = check_render(sim, traj, tmp_path / "render", max_frames=2)
    assert any(p.name == "force_depth.png" for p in done.images)


def test_stiffer_cheese_resists_the_wire_more(sweep) -> None:
    for name in ("peak_force", "mean_cut_force", "contact_stiffness", "cut_work"):
        assert feat(sweep, "E_hi", name) > feat(sweep, "E_lo", name), name
    assert feat(sweep, "E_hi", "settle_drop") < feat(sweep, "E_lo", "settle_drop")


def test_the_board_weighs_the_cheese(sweep) -> None:
    """resting_load is the block's weight (volume 48 cm^3 x rho x g), to 10 %; a force feature that
    separates rho from E (the two only meet as E/rho in the wave speed)."""
    for row, rho in (("rho_lo", 950.0), ("rho_hi", 1250.0)):
        weight = 0.06 * 0.04 * 0.02 * rho * 9.81
        assert feat(sweep, row, "resting_load") == pytest.approx(weight, rel=0.1)


def test_friction_drags_the_sliding_wire(sweep) -> None:
    """The wire slides along its axis while pressing: the drag it feels grows with the friction."""
    lo, hi = feat(sweep, "friction_lo", "slice_drag_ratio"), feat(sweep, "friction_hi", "slice_drag_ratio")
    assert abs(lo) < 0.05 and hi > 0.3


def test_runs_record_cost_and_provenance(sweep) -> None:
    res = sweep["E_hi"][0]
    assert res.ok and res.stats.simulator == "cheese_cut" and res.stats.preset == "tiny"
    assert res.stats.backend == "taichi" and res.stats.device.startswith("cpu")
    assert res.stats.substeps > sweep["E_lo"][0].stats.substeps      # stiffer -> smaller dt -> more substeps
    assert res.trajectory.extra["dt"] <= 0.1 * SPACE.to_mapping(res.params)["eta"] + 1e-12


def test_bad_input(sim) -> None:
    with pytest.raises(ParameterRangeError):
        sim.simulate(np.array([[1e9, 0.3, 1.0, 0.2, 0.1, 0.01, 0.2]]))
    with pytest.raises(ValueError, match="Did you mean 'tiny'"):
        CheeseCutSimulator(preset="tinny")


def test_listed_from_its_own_distribution() -> None:
    res = subprocess.run([sys.executable, "-m", "invphys.cli", "plugins", "--json"], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    found = {(p["kind"], p["name"]): p for p in json.loads(res.stdout)}
    assert found[("simulator", "cheese_cut")]["distribution"] == "invphys-cheese-cut"
    assert found[("feature_extractor", "cheese_cut_features")]["distribution"] == "invphys-cheese-cut"
