"""``stream_until_broken``: the shared first half of streaming rows (dataset workers, the simulator validator),
with the toy oscillator's real runs: a stream that breaks ends quietly with the rows it returned, a user error
propagates, and rows a stream never returned are re-run instead of lost."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from test_dataset_toy import StreamingOscillator, ToyFeatures, ToyOscillator

from invphys.core.errors import InvphysError, SimulationFailed
from invphys.core.stream import stream_until_broken, unreturned
from invphys.plugins.executors._batch import simulate_batch, stream_rows


def _params(n: int) -> np.ndarray:
    sim = ToyOscillator(substeps=8)
    return sim.parameter_space().denormalize(np.random.default_rng(5).random((n, sim.parameter_space().dim)))


class _Stream(StreamingOscillator):
    """Returns its last ``keep`` rows (last first), then raises ``error`` (None: ends without the others)."""

    name = "partial_stream"

    def __init__(self, keep: int, error: Exception | None, **settings) -> None:
        super().__init__(**settings)
        self.keep, self.error = keep, error

    def simulate_stream(self, params, batch_size=None):
        results = ToyOscillator.simulate(self, params)
        for n, i in enumerate(reversed(range(len(results)))):
            if n == self.keep:
                if self.error is not None:
                    raise self.error
                return
            yield i, results[i]


def test_a_broken_stream_ends_quietly_with_the_rows_it_returned(caplog) -> None:
    seen: set[int] = set()
    with caplog.at_level(logging.WARNING, logger="invphys.core.stream"):
        got = list(stream_until_broken(_Stream(2, SimulationFailed("nan"), substeps=8), _params(5), 2, seen))
    assert [i for i, _ in got] == [4, 3] and seen == {3, 4}
    assert unreturned(5, seen) == [0, 1, 2]
    assert "broke after 2 of 5 rows" in caplog.text


def test_a_user_error_in_the_stream_propagates() -> None:
    with pytest.raises(InvphysError, match="bad option"):
        list(stream_until_broken(_Stream(1, InvphysError("bad option"), substeps=8), _params(3), 2, set()))


def test_an_error_of_the_caller_is_not_taken_for_a_broken_stream() -> None:
    rows = stream_until_broken(StreamingOscillator(substeps=8), _params(3), 2, set())
    next(rows)
    with pytest.raises(ValueError, match="caller"):
        rows.throw(ValueError("caller"))


@pytest.mark.parametrize("error", [SimulationFailed("nan"), None], ids=["raised", "ended short"])
def test_dataset_rows_a_stream_did_not_return_are_simulated_in_batches(error) -> None:
    params, ext = _params(6), ToyFeatures()
    got = dict(stream_rows(_Stream(2, error, substeps=8), ext, params, 2))
    ref = simulate_batch(ToyOscillator(substeps=8), ext, params)
    assert sorted(got) == list(range(6))   # every row once: none lost when the stream stopped short
    np.testing.assert_array_equal(np.stack([got[i].features for i in range(6)]),
                                  np.stack([r.features for r in ref]))
