"""The extraction timeout where features are extracted in the process that simulates (``extract_workers: 0``
of ``local``, the ``process`` executor's workers, Ray tasks and actors, the simulator validator): a stuck
extractor makes its run a recorded failure naming the timeout, every other row keeps its features, and the
run goes on (before, only extraction worker processes had a timeout: these runs hung for good)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
from test_dataset_toy import FEATURES, SIM, ToyFeatures, ToyOscillator

from invphys.core.dataset import DatasetStore
from invphys.core.interfaces import PluginConfig
from invphys.data.generate import generate_dataset
from invphys.plugins.executors import LocalExecutor, ProcessExecutor, RayActorsExecutor, RayExecutor

TESTS = str(Path(__file__).resolve().parent)


class StuckFeatures(ToyFeatures):
    """The toy's features; for a run whose last frame's first particle is beyond ``limit``, extraction never
    returns: it sleeps in a loop that swallows every ``Exception`` (so a timeout must not be one)."""

    name = "stuck_toy_features"

    class Config(PluginConfig):
        limit: float = 0.5
        native: bool = False   # block SIGALRM first, as native code that never returns to Python would

    def extract(self, trajectory):
        if abs(float(trajectory.positions[-1, 0, 0])) > self.config.limit:
            if self.config.native:
                import signal

                signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
            while True:
                try:
                    time.sleep(3600)
                except Exception:
                    pass
        return ToyFeatures.extract(self, trajectory)


STUCK = {"type": "test_extract_timeout:StuckFeatures", "limit": 0.5}


def _params(n: int = 12) -> np.ndarray:
    space = ToyOscillator().parameter_space()
    unit = np.random.default_rng(4).random((n, 3))
    unit[3, 0], unit[3, 2] = 0.99, 0.0  # a stiff light oscillator blows up (omega dt > 2)
    return space.denormalize(unit)


def _plain() -> dict:
    return dict(LocalExecutor().run({"type": SIM, "substeps": 1}, {"type": FEATURES}, _params(), 5))


def _stuck_rows() -> set[int]:
    picky = {"type": "test_extract_pool:PickyFeatures", "limit": 0.5}
    got = dict(LocalExecutor().run({"type": SIM, "substeps": 1}, picky, _params(), 5))
    return {i for i, r in got.items() if not r.ok and "picky" in r.failure}


def _check(got: dict, expect: str = "ExtractionTimedOut: feature extraction took longer than 1 s") -> None:
    plain, stuck = _plain(), _stuck_rows()
    assert len(stuck) == 1 and sorted(got) == list(range(12))
    for i in range(12):
        if i in stuck:
            assert not got[i].ok and expect in got[i].failure, got[i].failure
        else:   # every other row as without the stuck extractor
            assert got[i].ok == plain[i].ok and got[i].failure == plain[i].failure, got[i].failure
            if plain[i].ok:
                np.testing.assert_array_equal(got[i].features, plain[i].features)


def test_in_process_extraction_is_interrupted_and_the_dataset_goes_on(tmp_path) -> None:
    start = time.monotonic()
    summary = generate_dataset(tmp_path / "ds", {"type": SIM, "substeps": 1}, features=STUCK, n=12,
                               batch_size=5, executor={"type": "local", "extract_timeout_s": 1.0},
                               progress=False, seed=4)
    assert time.monotonic() - start < 30
    frame = DatasetStore(tmp_path / "ds").frame()
    assert len(frame) == 12 == summary.ran
    timed_out = frame[frame["failure"].fillna("").str.contains("took longer than 1 s")]
    assert len(timed_out) >= 1 and (timed_out["status"] == "failed").all()
    assert (frame["status"] == "ok").sum() >= 6   # the rows after the stuck one were simulated and stored
    # the same rows through the executor: only the stuck run failed, the others are unchanged
    got = dict(LocalExecutor(extract_timeout_s=1.0).run({"type": SIM, "substeps": 1}, STUCK, _params(), 5))
    _check(got)
    import signal

    assert signal.getsignal(signal.SIGALRM) == signal.SIG_DFL and signal.getitimer(signal.ITIMER_REAL) == (0, 0)


def test_in_process_streaming_and_the_validator_are_interrupted() -> None:
    from invphys.plugins.executors._batch import stream_rows
    from invphys.plugins.validators.simulator import SimulatorValidator

    sim = ToyOscillator(substeps=1)
    got = dict(stream_rows(sim, StuckFeatures(limit=0.5), _params(), 4, timeout_s=1.0))
    _check(got)
    val = SimulatorValidator(batch_size=5, extract_timeout_s=1.0)
    unit = sim.parameter_space().normalize(_params())
    out = val.simulate_features(unit, sim, StuckFeatures(limit=0.5))
    stuck = [r for r, f in enumerate(out.failures) if f and "took longer than 1 s" in f]
    assert stuck == sorted(_stuck_rows()) and np.isnan(out.features[stuck[0]]).all()


def test_process_executor_interrupts_a_stuck_extraction_in_its_worker() -> None:
    ex = ProcessExecutor(workers=2, extract_timeout_s=1.0)
    _check(dict(ex.run({"type": SIM, "substeps": 1}, STUCK, _params(), 5)))


def test_process_executor_ends_a_worker_stuck_in_native_code() -> None:
    """SIGALRM blocked (as in native code that never returns): the worker is ended after the timeout plus a
    grace period (here 1 + 1 s) and the rows of its batch are re-run alone; only the stuck row fails."""
    ex = ProcessExecutor(workers=2, extract_timeout_s=1.0)
    got = dict(ex.run({"type": SIM, "substeps": 1}, {**STUCK, "native": True}, _params(), 5))
    _check(got, expect="past the extraction timeout (1 s")


def test_ray_tasks_and_actors_interrupt_a_stuck_extraction(monkeypatch) -> None:
    pytest.importorskip("ray")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([TESTS, os.environ.get("PYTHONPATH", "")]))
    import ray

    try:
        tasks = RayExecutor(num_cpus=2, max_in_flight=2, extract_timeout_s=1.0, shutdown=False)
        _check(dict(tasks.run({"type": SIM, "substeps": 1}, STUCK, _params(), 5)))
        actors = RayActorsExecutor(num_gpus=0, actors=2, extract_timeout_s=1.0)
        _check(dict(actors.run({"type": SIM, "substeps": 1}, STUCK, _params(), 5)))
    finally:
        ray.shutdown()


def test_a_disposable_process_with_captured_stderr_still_extracts(monkeypatch) -> None:
    """Where ``sys.stderr`` has no file descriptor (a test runner's or a CLI runner's capture), the hard stop is
    armed on the real stderr or not at all: the extraction runs (it raised 'fileno' and failed every row)."""
    import io

    from invphys.plugins.executors import _deadline

    monkeypatch.setattr(_deadline, "DISPOSABLE", True)
    monkeypatch.setattr("sys.stderr", io.StringIO())
    assert _deadline.call(lambda x: x + 1, 5.0, 41) == 42
