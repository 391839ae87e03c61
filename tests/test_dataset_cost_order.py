"""Dataset generation starts the costliest runs first when the simulator estimates costs, so that each
lock-step batch holds runs of similar cost, within windows of a few batches in design order (a session
stopped early stored about the design's first rows, not its costliest); the stored rows are the same as in
design order."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest
from test_dataset_toy import FEATURES, SIM, ToyOscillator

from invphys.core.dataset import DatasetStore
from invphys.core.errors import InvphysError
from invphys.data.generate import generate_dataset


class CostedToy(ToyOscillator):
    """The toy oscillator with a cost estimate (its stiffness k) and a log of the batches it simulated."""

    batches: ClassVar[list[np.ndarray]] = []

    def estimate_cost(self, params: np.ndarray) -> np.ndarray:
        return np.atleast_2d(params)[:, 0]

    def simulate(self, params, on_result=None):
        CostedToy.batches.append(np.atleast_2d(params)[:, 0].copy())
        return super().simulate(params, on_result)


class MiscountingToy(ToyOscillator):
    def estimate_cost(self, params: np.ndarray) -> np.ndarray:
        return np.ones(1)


def test_costliest_runs_go_first_in_batches_of_similar_cost(tmp_path) -> None:
    CostedToy.batches.clear()
    feats = {"type": FEATURES}
    generate_dataset(tmp_path / "costed", {"type": f"{__name__}:CostedToy", "substeps": 5}, feats, n=8,
                     batch_size=3, progress=False)
    assert [len(b) for b in CostedToy.batches] == [3, 3, 2]
    k = np.concatenate(CostedToy.batches)
    assert np.all(np.diff(k) <= 0), k   # costliest first across and within batches
    generate_dataset(tmp_path / "plain", {"type": SIM, "substeps": 5}, feats, n=8, batch_size=3, progress=False)
    costed = DatasetStore(tmp_path / "costed").arrays(ok_only=False)
    plain = DatasetStore(tmp_path / "plain").arrays(ok_only=False)
    np.testing.assert_array_equal(costed.theta, plain.theta)
    np.testing.assert_array_equal(costed.y, plain.y)


def test_a_cost_estimate_of_the_wrong_length_is_one_clear_error(tmp_path) -> None:
    with pytest.raises(InvphysError, match="estimate_cost gave 1 values for 4 rows"):
        generate_dataset(tmp_path / "bad", {"type": f"{__name__}:MiscountingToy", "substeps": 5},
                         {"type": FEATURES}, n=4, batch_size=2, progress=False)


def test_costliest_first_only_within_windows_so_a_stopped_session_is_not_a_biased_sample(tmp_path) -> None:
    """Rows go costliest first within windows of COST_WINDOW_BATCHES batches taken in design order: the rows
    simulated first are the design's first window, not the costliest rows of the whole design."""
    from invphys.data.generate import COST_WINDOW_BATCHES

    CostedToy.batches.clear()
    feats = {"type": FEATURES}
    n = 3 * COST_WINDOW_BATCHES
    generate_dataset(tmp_path / "costed", {"type": f"{__name__}:CostedToy", "substeps": 5}, feats, n=n,
                     batch_size=1, progress=False)
    generate_dataset(tmp_path / "plain", {"type": SIM, "substeps": 5}, feats, n=n, batch_size=n, progress=False)
    frame = DatasetStore(tmp_path / "plain").frame().sort_values("sample_index")
    design = frame[next(c for c in frame.columns if c.startswith("p_"))].to_numpy()   # k of each design row
    ran = np.concatenate(CostedToy.batches)
    w = COST_WINDOW_BATCHES
    expected = np.concatenate([-np.sort(-design[i:i + w]) for i in range(0, n, w)])
    np.testing.assert_allclose(ran, expected)
    assert not np.all(np.diff(ran) <= 0)   # not one global costliest-first order
