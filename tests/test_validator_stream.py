"""The simulator validator streams a ``native_stream`` simulator (continuous batching, as dataset generation
runs it) instead of waiting on each chunk's slowest run; a stream that raises hands its unreturned rows to
the chunked path, a failing row alone. The real orange peel: examples/orange_peel/tests/test_orange_validate_stream.py."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from test_dataset_toy import StreamingOscillator, ToyFeatures, ToyOscillator

from invphys.core.errors import SimulationFailed
from invphys.plugins.validators.simulator import SimulatorValidator


def _theta(n: int) -> np.ndarray:
    return np.random.default_rng(3).random((n, ToyOscillator().parameter_space().dim))


def test_a_native_stream_runs_every_row_in_one_stream_with_the_chunked_features() -> None:
    theta, ext = _theta(7), ToyFeatures()
    StreamingOscillator.streams.clear()
    seen: list[int] = []
    streamed = SimulatorValidator(batch_size=2).simulate_features(
        theta, StreamingOscillator(substeps=8), ext, on_record=lambda r, *_: seen.append(r))
    assert StreamingOscillator.streams == [7]            # one stream over all rows, not one per chunk of 2
    assert sorted(seen) == list(range(7)) and seen != sorted(seen)   # each row once, as its run ends
    chunked = SimulatorValidator(batch_size=2).simulate_features(theta, ToyOscillator(substeps=8), ext)
    np.testing.assert_array_equal(streamed.features, chunked.features)
    assert streamed.failures == [None] * 7


def test_a_stream_with_extraction_workers_waits_for_every_rows_features() -> None:
    """The rows whose features are still in the extraction processes when the stream ends are collected (they
    came back as NaN rows without a failure: measured on a GPU, 24 of 200 answers)."""
    theta, ext = _theta(9), ToyFeatures()
    streamed = SimulatorValidator(batch_size=4, extract_workers=2).simulate_features(
        theta, StreamingOscillator(substeps=8), ext)
    chunked = SimulatorValidator(batch_size=4).simulate_features(theta, ToyOscillator(substeps=8), ext)
    np.testing.assert_array_equal(streamed.features, chunked.features)
    assert streamed.failures == chunked.failures


class BreakingStream(StreamingOscillator):
    """Its stream returns its last two rows and then raises (a run that blew up mid-stream); ``bad_row``
    also fails on the batch API. ``chunks``: the rows each batch call got."""

    name = "breaking_stream"
    chunks: ClassVar[list[int]] = []

    def simulate_stream(self, params, batch_size=None):
        results = ToyOscillator.simulate(self, params)
        for n, i in enumerate(reversed(range(len(results)))):
            if n == 2:
                raise SimulationFailed("nan in the stress")
            yield i, results[i]

    def simulate(self, params, on_result=None):
        type(self).chunks.append(len(params))
        if any(np.allclose(p, self.bad_row) for p in np.atleast_2d(params)):
            raise SimulationFailed("one row blew up")
        return super().simulate(params, on_result)


def test_a_stream_that_raises_hands_its_unreturned_rows_to_chunks_and_a_failing_row_fails_alone() -> None:
    theta, ext, bad = _theta(6), ToyFeatures(), 1
    sim = BreakingStream(substeps=8)
    sim.bad_row = sim.parameter_space().denormalize(theta[bad:bad + 1])[0]
    BreakingStream.chunks.clear()
    got = SimulatorValidator(batch_size=2).simulate_features(theta, sim, ext)
    ref = SimulatorValidator(batch_size=6).simulate_features(theta, ToyOscillator(substeps=8), ext)
    ok = [r for r in range(6) if r != bad]
    np.testing.assert_array_equal(got.features[ok], ref.features[ok])
    assert got.failures[bad] == "one row blew up" and np.isnan(got.features[bad]).all()
    assert all(got.failures[r] is None for r in ok)
    # rows 5 and 4 came from the stream; 0-3 in chunks of 2, the chunk of the bad row (0, 1) re-run row by row
    assert BreakingStream.chunks == [2, 1, 1, 2]


def test_inverter_validate_extracts_in_worker_processes_with_the_same_answers(tmp_path_factory) -> None:
    import pytest
    from test_inverter_support import toy_run

    import invphys
    from invphys.core.dataset import DatasetStore
    from invphys.core.errors import InvphysError

    run = toy_run(tmp_path_factory.getbasetemp())
    inv = invphys.load_inverter(run / "inverter")
    y = DatasetStore(next((run / "dataset").rglob("_manifest.json")).parent).arrays(ok_only=True).y[:3]
    r_actual = []
    for workers in (0, 1):
        res = inv.validate(inv.invert_many(y, top_k=2, seed=0), batch_size=2, extract_workers=workers)
        r_actual.append([c.r_actual for r in res for c in r.candidates])
    assert r_actual[0] == r_actual[1] and all(np.isfinite(r_actual[0]))
    with pytest.raises(InvphysError, match="extract_workers must be >= 0"):
        inv.validate(inv.invert_many(y[:1]), extract_workers=-1)


def test_an_error_of_the_callers_callback_is_not_taken_for_a_broken_stream() -> None:
    """Only the stream's own failures send rows to the chunked path; a progress callback that raises stops the
    validation with its error (swallowed, its row would have stayed NaN without a failure)."""
    import pytest

    calls: list[int] = []

    def on_run(row: int) -> None:   # breaks once (the old code swallowed it and returned that row as NaN)
        calls.append(row)
        if len(calls) == 1:
            raise ValueError("progress bar broke")

    with pytest.raises(ValueError, match="progress bar broke"):
        SimulatorValidator(batch_size=2).simulate_features(_theta(3), StreamingOscillator(substeps=8), ToyFeatures(),
                                                           on_run=on_run)


def test_invert_validate_workers_on_the_command_line(tmp_path_factory) -> None:
    """``invphys invert --validate --validate-workers 1`` validates through an extraction process with the
    in-thread answer; a negative count is one error line, exit 2."""
    import json

    from test_inverter_support import toy_run
    from typer.testing import CliRunner

    from invphys.cli import app
    from invphys.core.dataset import DatasetStore

    run = toy_run(tmp_path_factory.getbasetemp())
    bundle = run / "inverter"
    y = DatasetStore(next((run / "dataset").rglob("_manifest.json")).parent).arrays(ok_only=True).y[0]
    import invphys

    names = invphys.load_inverter(bundle).feature_names
    feats = [a for n, v in zip(names, y, strict=True) for a in ("--feature", f"{n}={v}")]
    runner = CliRunner()
    r_actual = []
    for workers in ("0", "1"):
        out = runner.invoke(app, ["invert", str(bundle), *feats, "--validate", "--validate-workers", workers, "--json"])
        assert out.exit_code == 0, out.output
        r_actual.append(json.loads(out.stdout)["results"][0]["candidates"][0]["r_actual"])
    assert r_actual[0] == r_actual[1] and r_actual[0] > 0
    out = runner.invoke(app, ["invert", str(bundle), *feats, "--validate", "--validate-workers", "-1"])
    assert out.exit_code == 2 and "--validate-workers" in out.output and "Traceback" not in out.output, out.output
