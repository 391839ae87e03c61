"""The toy spring meets invphys's contracts (run with pytest in the package's folder)."""

import numpy as np
import pytest
from invphys_toy_spring.features import SpringFeatures
from invphys_toy_spring.simulator import SpringSimulator

from invphys.core.errors import ParameterRangeError
from invphys.testing import (
    check_deterministic,
    check_feature_extractor,
    check_plugin_class,
    check_render,
    check_simulator,
    check_trajectory_file,
)


def test_conformance(tmp_path):
    check_plugin_class(SpringSimulator)
    check_plugin_class(SpringFeatures)
    sim = SpringSimulator()
    results = check_simulator(sim, n_runs=4)
    check_deterministic(sim)
    y = check_feature_extractor(SpringFeatures(), results)
    assert y.shape == (4, 3)
    check_trajectory_file(results[0].trajectory, tmp_path)
    done = check_render(sim, results[0].trajectory, tmp_path / "render", max_frames=3)
    assert len(done.images) == 4  # 3 frames and the series plot


def test_failures_and_bad_input():
    stiff_and_light = [[1000.0, 0.01, 0.1]]
    res = SpringSimulator(substeps=1).simulate(stiff_and_light)[0]  # omega dt = 2.5: unstable
    assert not res.ok and res.failure.startswith("blow-up:") and res.trajectory is None
    assert SpringSimulator().simulate(stiff_and_light)[0].ok  # 10 substeps per frame: stable
    with pytest.raises(ParameterRangeError):
        SpringSimulator().simulate([[5.0, 0.1, 1.0]])  # k below its range


def test_features_follow_the_physics():
    sim, ex = SpringSimulator(), SpringFeatures()
    (soft, stiff) = sim.simulate([[50.0, 0.05, 1.0], [800.0, 0.05, 1.0]])
    y_soft, y_stiff = ex.extract(soft.trajectory), ex.extract(stiff.trajectory)
    assert y_stiff[0] == pytest.approx(800.0 * 0.05)  # peak force k x0
    quarter = np.pi / 2 / np.sqrt(50.0)  # a quarter period of the undamped spring
    assert y_soft[1] == pytest.approx(quarter, rel=0.02) and y_stiff[1] < y_soft[1]
    damped = ex.extract(sim.simulate([[50.0, 0.4, 1.0]])[0].trajectory)
    assert 0.0 < y_soft[2] < damped[2] < 1.0  # more damping, more energy lost
