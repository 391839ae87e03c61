"""Feature extraction in worker processes (``executor: {type: local, extract_workers: N}``): the same
features and failures as extraction in this process, on the batch and the streaming path, and an
extractor that raises in a worker becomes that run's recorded failure."""

from __future__ import annotations

import numpy as np
import pytest
from test_dataset_toy import FEATURES, SIM, ToyFeatures, ToyOscillator

from invphys.core.interfaces import PluginConfig


class PickyFeatures(ToyFeatures):
    """The toy's features, raising for runs whose first particle starts its last frame above ``limit``."""

    name = "picky_toy_features"

    class Config(PluginConfig):
        limit: float = 0.2

    def extract(self, trajectory):
        if abs(float(trajectory.positions[-1, 0, 0])) > self.config.limit:
            raise ValueError("picky: amplitude too large")
        return super().extract(trajectory)


class DyingFeatures(PickyFeatures):
    """The toy's features; the process extracting a run that PickyFeatures refuses dies (as a crash in native
    code, or a kill for memory, would end it)."""

    name = "dying_toy_features"

    def extract(self, trajectory):
        if abs(float(trajectory.positions[-1, 0, 0])) > self.config.limit:
            import os

            os._exit(3)
        return ToyFeatures.extract(self, trajectory)


def _die_in_a_child(parent_pid: int):
    import os

    if os.getpid() != parent_pid:
        os._exit(5)   # a worker that dies while it starts (unpickling its extractor)
    return UnstartableFeatures()


class UnstartableFeatures(ToyFeatures):
    """The toy's features, as an instance that kills any other process that unpickles it."""

    name = "unstartable_toy_features"

    def __reduce__(self):
        import os

        return _die_in_a_child, (os.getpid(),)


class PidFeatures(ToyFeatures):
    """The id of the process that extracted the run (to see where extraction happens)."""

    name = "pid_toy_features"

    @property
    def feature_names(self) -> tuple[str, ...]:
        return ("pid",)

    def extract(self, trajectory):
        import os

        return np.array([float(os.getpid())])


def _params(n: int) -> np.ndarray:
    space = ToyOscillator().parameter_space()
    unit = np.random.default_rng(4).random((n, 3))
    unit[3, 0], unit[3, 2] = 0.99, 0.0  # a stiff light oscillator blows up (omega dt > 2)
    return space.denormalize(unit)


def _run(workers: int, features: dict, batch_size: int = 5) -> list:
    from invphys.plugins.executors.local import LocalExecutor

    ex = LocalExecutor(extract_workers=workers)
    return sorted(ex.run({"type": SIM, "substeps": 1}, features, _params(12), batch_size), key=lambda t: t[0])


def test_worker_extraction_equals_in_process_extraction() -> None:
    inline = _run(0, {"type": FEATURES})
    pooled = _run(2, {"type": FEATURES})
    assert [i for i, _ in pooled] == list(range(12))
    assert [r.ok for _, r in pooled] == [r.ok for _, r in inline]
    assert not pooled[3][1].ok and "blow-up" in pooled[3][1].failure
    for (_, a), (_, b) in zip(inline, pooled, strict=True):
        assert b.trajectory is None
        if a.ok:
            np.testing.assert_array_equal(a.features, b.features)


def test_extraction_happens_in_the_worker_processes() -> None:
    import os

    inline = {r.features[0] for _, r in _run(0, {"type": "test_extract_pool:PidFeatures"}) if r.ok}
    pooled = {r.features[0] for _, r in _run(2, {"type": "test_extract_pool:PidFeatures"}) if r.ok}
    assert inline == {float(os.getpid())}
    assert float(os.getpid()) not in pooled and 1 <= len(pooled) <= 2


def test_an_extractor_error_in_a_worker_is_that_runs_failure() -> None:
    block = {"type": "test_extract_pool:PickyFeatures", "limit": 0.05}
    inline = _run(0, block)
    pooled = _run(2, block)
    failed = [i for i, r in inline if not r.ok and "picky" in r.failure]
    assert 0 < len(failed) < 11  # some rows fail in extraction, others do not
    assert [r.failure for _, r in pooled] == [r.failure for _, r in inline]
    for (_, a), (_, b) in zip(inline, pooled, strict=True):
        if a.ok:
            np.testing.assert_array_equal(a.features, b.features)


def test_streaming_rows_through_a_pool_yields_each_row_once_with_its_features() -> None:
    from invphys.plugins.executors._batch import stream_rows
    from invphys.plugins.executors._extract_pool import ExtractionPool

    sim, ext = ToyOscillator(substeps=1), ToyFeatures()
    params = _params(12)
    with ExtractionPool({"type": FEATURES}, 2) as pool:
        got = dict(stream_rows(sim, ext, params, 4, pool=pool))
    assert sorted(got) == list(range(12))
    for i, res in got.items():
        direct = sim.simulate(params[i][None])[0]
        assert res.ok == direct.ok
        if res.ok:
            np.testing.assert_array_equal(res.features, ext.extract(direct.trajectory))


def _validate(workers: int, extractor, keep=frozenset({0, 1})):
    from invphys.plugins.validators.simulator import SimulatorValidator

    sim = ToyOscillator(substeps=1)
    unit = sim.parameter_space().normalize(_params(12))
    records: dict[int, tuple] = {}

    def on_record(r, feats, failure, stats):
        assert r not in records  # once per row
        records[r] = (None if feats is None else feats.copy(), failure)

    val = SimulatorValidator(batch_size=5, extract_workers=workers)
    got = val.simulate_features(unit, sim, extractor, keep_trajectories=set(keep), on_record=on_record)
    return got, records


def test_validator_extraction_in_workers_equals_in_thread_extraction() -> None:
    inline, rec_inline = _validate(0, ToyFeatures())
    pooled, rec_pooled = _validate(2, ToyFeatures())
    np.testing.assert_array_equal(inline.features, pooled.features)
    assert inline.failures == pooled.failures and 1 <= sum(f is not None for f in pooled.failures) < 12
    assert sorted(rec_pooled) == list(range(12))
    for r in range(12):
        assert rec_pooled[r][1] == rec_inline[r][1]
        if rec_inline[r][0] is not None:
            np.testing.assert_array_equal(rec_pooled[r][0], rec_inline[r][0])
    for r in (0, 1):  # kept rows: their trajectories, as in the thread
        assert (pooled.trajectories[r] is None) == (pooled.failures[r] is not None)
        if pooled.trajectories[r] is not None:
            np.testing.assert_array_equal(pooled.trajectories[r].positions, inline.trajectories[r].positions)
    assert any(t is not None for t in pooled.trajectories[:2])
    assert all(t is None for t in pooled.trajectories[2:])


def test_validator_extracts_in_its_worker_processes_and_reuses_them() -> None:
    import os

    from invphys.plugins.validators.simulator import SimulatorValidator

    sim = ToyOscillator(substeps=1)
    unit = sim.parameter_space().normalize(_params(12))
    val = SimulatorValidator(batch_size=4, extract_workers=2)
    first = val.simulate_features(unit, sim, PidFeatures())
    second = val.simulate_features(unit, sim, PidFeatures())
    pids = {p for p in np.concatenate([first.features[:, 0], second.features[:, 0]]) if np.isfinite(p)}
    assert float(os.getpid()) not in pids and 1 <= len(pids) <= 2  # one pool for both calls


def test_an_extractor_error_in_a_validator_worker_is_raised_as_in_thread() -> None:
    import pytest

    for workers in (0, 2):
        with pytest.raises(ValueError, match="picky"):
            _validate(workers, PickyFeatures(limit=0.05), keep=frozenset())


def _stream_through(pool_kwargs: dict, features: dict | None = None) -> tuple[dict, list[str]]:
    from invphys.plugins.executors._batch import stream_rows
    from invphys.plugins.executors._extract_pool import ExtractionPool

    sim, ext = ToyOscillator(substeps=1), ToyFeatures()
    with ExtractionPool(features or {"type": FEATURES}, 2, **pool_kwargs) as pool:
        got = dict(stream_rows(sim, ext, _params(12), 4, pool=pool))
        blocks = list(pool._blocks._all) if pool._blocks is not None else []
        names = [b.name for b in blocks]
        assert all(b in pool._blocks._free for b in blocks)   # every block given back once its run resolved
        created = pool._blocks.created if pool._blocks is not None else 0
    return got, names if created else []


def test_trajectories_through_shared_memory_give_the_pickled_paths_features_and_leave_nothing() -> None:
    from multiprocessing import shared_memory

    import pytest

    pickled, none = _stream_through({"min_shared_bytes": None})
    shared, names = _stream_through({"min_shared_bytes": 0})
    assert none == [] and 1 <= len(names) <= 2 * 2 + 2   # blocks were used, and reused (12 runs)
    assert sorted(shared) == sorted(pickled) == list(range(12))
    for i in range(12):
        assert shared[i].ok == pickled[i].ok and shared[i].failure == pickled[i].failure
        if pickled[i].ok:
            np.testing.assert_array_equal(shared[i].features, pickled[i].features)
    for name in names:   # closing the pool unlinked every block
        with pytest.raises(FileNotFoundError):
            shared_memory.SharedMemory(name=name)


def test_an_extractor_error_through_shared_memory_is_that_runs_failure() -> None:
    block = {"type": "test_extract_pool:PickyFeatures", "limit": 0.05}
    pickled, _ = _stream_through({"min_shared_bytes": None}, block)
    shared, names = _stream_through({"min_shared_bytes": 0}, block)
    assert names
    failed = [i for i, r in shared.items() if not r.ok and "picky" in r.failure]
    assert 0 < len(failed) < 11
    assert [shared[i].failure for i in range(12)] == [pickled[i].failure for i in range(12)]


@pytest.mark.parametrize("min_shared_bytes", [None, 0], ids=["pickled", "shared"])
def test_a_worker_that_dies_fails_only_the_run_that_killed_it(min_shared_bytes) -> None:
    """A dead worker used to break the pool for good, failing every later run; now the pool is replaced, the
    runs it held are retried alone, only the runs that kill a process fail, and the rest keep their features."""
    picky, _ = _stream_through({"min_shared_bytes": None}, {"type": "test_extract_pool:PickyFeatures", "limit": 0.05})
    dying, _ = _stream_through({"min_shared_bytes": min_shared_bytes},   # every block given back (checked there)
                               {"type": "test_extract_pool:DyingFeatures", "limit": 0.05})
    killers = {i for i, r in picky.items() if not r.ok and "picky" in r.failure}
    assert 0 < len(killers) < 11 and sorted(dying) == list(range(12))
    for i in range(12):
        if i in killers:
            assert not dying[i].ok and "ExtractionWorkerDied" in dying[i].failure, dying[i].failure
        else:
            assert dying[i].ok == picky[i].ok and dying[i].failure == picky[i].failure, dying[i].failure
            if picky[i].ok:
                np.testing.assert_array_equal(dying[i].features, picky[i].features)


def test_a_worker_that_dies_in_the_validator_is_that_rows_failure_and_the_pool_goes_on() -> None:
    from invphys.plugins.validators.simulator import SimulatorValidator

    sim = ToyOscillator(substeps=1)
    unit = sim.parameter_space().normalize(_params(12))
    inline = SimulatorValidator(batch_size=5).simulate_features(unit, sim, ToyFeatures(), keep_trajectories=True)
    killers = {r for r, t in enumerate(inline.trajectories) if t is not None and abs(float(t.positions[-1, 0, 0])) > 0.05}
    assert 0 < len(killers) < 11
    val = SimulatorValidator(batch_size=5, extract_workers=2)
    for _ in range(2):   # the validator keeps its pool between calls: the replaced one serves the second
        got = val.simulate_features(unit, sim, DyingFeatures(limit=0.05))
        for r in range(12):
            if r in killers:
                assert "process died on this run" in got.failures[r] and np.isnan(got.features[r]).all()
            else:
                assert got.failures[r] == inline.failures[r]
                np.testing.assert_array_equal(got.features[r], inline.features[r])
    assert next(iter(val._pools.values())).renewed >= 1


def test_an_extractor_registered_only_here_stops_extraction_in_workers_with_one_clear_error() -> None:
    """A plugin registered by hand is not in a spawned worker's registry; that used to fail every run as a
    broken pool (and, retried alone, as a death of each run). It is the user's to fix: one InvphysError."""
    from invphys import registry
    from invphys.core.errors import InvphysError

    class HandRegisteredFeatures(ToyFeatures):
        name = "hand_registered_toy_features"

    with registry.registered(HandRegisteredFeatures):
        assert len(_run(0, {"type": "hand_registered_toy_features"})) == 12   # fine in this process
        with pytest.raises(InvphysError, match=r"cannot build the extractor .*hand_registered_toy_features.*"
                                               r"registered by hand"):
            _run(2, {"type": "hand_registered_toy_features"})


def test_workers_that_die_while_starting_stop_extraction_instead_of_failing_each_run() -> None:
    from invphys.core.errors import InvphysError
    from invphys.plugins.executors._batch import stream_rows
    from invphys.plugins.executors._extract_pool import ExtractionPool

    sim = ToyOscillator(substeps=1)
    with ExtractionPool(UnstartableFeatures(), 2, min_shared_bytes=None) as pool:
        with pytest.raises(InvphysError, match="died starting"):
            dict(stream_rows(sim, ToyFeatures(), _params(12), 4, pool=pool))
    assert pool.retried <= 2 * 2 + 2   # the runs the broken pool held at most, not all twelve


def test_pack_round_trips_arrays_as_views_of_a_reused_block() -> None:
    from invphys.plugins.executors import _shared_blocks
    from invphys.plugins.executors._shared_blocks import SharedBlocks, pack, unpack

    rng = np.random.default_rng(1)
    obj = {"f32": rng.normal(size=(5, 7, 3)).astype(np.float32), "i8": np.arange(11, dtype=np.int8),
           "fortran": np.asfortranarray(rng.normal(size=(4, 6))), "strided": rng.normal(size=(9, 4))[::2],
           "name": "run", "n": 3}
    blocks = SharedBlocks(max_blocks=1)
    try:
        assert pack(obj, blocks, min_bytes=1 << 30) is None          # too small to be worth a block
        assert blocks.created == 0
        data, block, spans = pack(obj, blocks, min_bytes=0)
        assert blocks.acquire(8) is None                              # the only block is lent out
        back = unpack(data, block.name, spans)
        for key in ("f32", "i8", "fortran", "strided"):
            np.testing.assert_array_equal(back[key], obj[key])
            assert back[key].dtype == obj[key].dtype
        assert back["fortran"].flags.f_contiguous and (back["name"], back["n"]) == ("run", 3)
        assert all(a % 64 == 0 for a, _ in spans)
        np.frombuffer(block.buf, np.uint8)[:] = 0          # the unpacked arrays are views of the block's pages
        assert not back["f32"].any() and not back["i8"].any()
        del back
        _shared_blocks._ATTACHED.pop(block.name).close()   # this process attached it as a worker would
        blocks.release(block)
        again = pack(obj, blocks, min_bytes=0)
        assert again is not None and again[1] is block and blocks.created == 1   # reused
        blocks.release(block)
    finally:
        blocks.close()
    assert SharedBlocks(max_blocks=2, shm_dir="/no/such/dir").acquire(8) is None   # nowhere to put it: pickle


def test_a_pool_never_closed_unlinks_its_blocks_when_the_process_exits(tmp_path) -> None:
    import subprocess
    import sys
    from multiprocessing import shared_memory
    from pathlib import Path

    import pytest

    script = tmp_path / "keep_pool.py"
    script.write_text(
        "import sys\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from test_dataset_toy import FEATURES, ToyOscillator\n"
        "from invphys.plugins.executors._extract_pool import ExtractionPool\n"
        "if __name__ == '__main__':\n"
        "    pool = ExtractionPool({'type': FEATURES}, 1, min_shared_bytes=0)   # never closed, as the validator's\n"
        "    res = ToyOscillator(substeps=1).simulate(ToyOscillator().parameter_space().denormalize([[0.5, 0.5, 0.5]]))[0]\n"
        "    print(pool.extract(res.trajectory).result().shape, pool._blocks._all[0].name, flush=True)\n")
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    shape, name = run.stdout.split(") ")
    assert shape.startswith("(") and name.strip()
    assert "leaked" not in run.stderr and "Traceback" not in run.stderr, run.stderr
    with pytest.raises(FileNotFoundError):
        shared_memory.SharedMemory(name=name.strip())


class SleepyFeatures(PickyFeatures):
    """The toy's features; for a run PickyFeatures refuses, extraction never returns (a stuck extractor)."""

    name = "sleepy_toy_features"

    def extract(self, trajectory):
        if abs(float(trajectory.positions[-1, 0, 0])) > self.config.limit:
            import time

            while True:
                time.sleep(3600)
        return ToyFeatures.extract(self, trajectory)


SLEEPY = {"type": "test_extract_pool:SleepyFeatures", "limit": 0.5}   # one of _params(12)'s runs sleeps


def _check_only_the_stuck_run_failed(got: dict, stuck_error: str = "took longer than 1 s") -> None:
    inline = dict(_run(0, {"type": FEATURES}))
    stuck = {i for i, r in dict(_run(0, {"type": "test_extract_pool:PickyFeatures", "limit": 0.5})).items()
             if not r.ok and "picky" in r.failure}
    assert len(stuck) == 1 and sorted(got) == list(range(12))
    for i in range(12):
        if i in stuck:
            assert not got[i].ok and "ExtractionTimedOut" in got[i].failure and stuck_error in got[i].failure
        else:
            assert got[i].ok == inline[i].ok and got[i].failure == inline[i].failure, got[i].failure
            if inline[i].ok:
                np.testing.assert_array_equal(got[i].features, inline[i].features)


def test_an_extractor_that_never_returns_is_stopped_at_the_timeout_and_fails_only_its_run() -> None:
    """Before, a stuck extractor hung the dataset for good (no per-run timeout); now its process is killed,
    the run is a recorded failure, the other runs keep their features, and no process is left behind."""
    import multiprocessing
    import time

    from invphys.plugins.executors.local import LocalExecutor

    before = set(multiprocessing.active_children())   # another test's validator keeps its pool
    start = time.monotonic()
    ex = LocalExecutor(extract_workers=2, extract_timeout_s=1.0)
    got = dict(ex.run({"type": SIM, "substeps": 1}, SLEEPY, _params(12), 5))
    assert time.monotonic() - start < 90
    _check_only_the_stuck_run_failed(got)
    assert set(multiprocessing.active_children()) <= before   # the stuck process was stopped, not left sleeping


@pytest.mark.parametrize("min_shared_bytes", [None, 0], ids=["pickled", "shared"])
def test_a_stuck_run_in_a_stream_is_stopped_and_the_pool_goes_on(min_shared_bytes) -> None:
    from invphys.plugins.executors._extract_pool import ExtractionPool

    got, _ = _stream_through({"min_shared_bytes": min_shared_bytes, "timeout_s": 1.0}, SLEEPY)  # blocks given back
    _check_only_the_stuck_run_failed(got)
    with ExtractionPool({"type": FEATURES}, 1) as pool:
        assert pool.timeout_s == 600.0   # the documented default


def test_the_extraction_timeout_is_a_setting_with_a_documented_default() -> None:
    from invphys.core.errors import InvphysError
    from invphys.plugins.executors._extract_pool import DEFAULT_TIMEOUT_S, ExtractionPool
    from invphys.plugins.executors.local import LocalExecutor

    assert DEFAULT_TIMEOUT_S == 600.0 and LocalExecutor().config.extract_timeout_s == 600.0
    assert LocalExecutor(extract_timeout_s=None).config.extract_timeout_s is None
    with pytest.raises(Exception, match="greater than 0"):
        LocalExecutor(extract_timeout_s=0)
    with pytest.raises(InvphysError, match="timeout"):
        ExtractionPool({"type": FEATURES}, 1, timeout_s=-1)


def test_the_validator_stops_a_stuck_extraction_at_its_timeout() -> None:
    """The simulator validator's extraction processes take the same per-run timeout (it had the fixed default)."""
    from invphys.plugins.validators.simulator import SimulatorValidator

    sim = ToyOscillator(substeps=1)
    unit = sim.parameter_space().normalize(_params(12))
    val = SimulatorValidator(batch_size=5, extract_workers=2, extract_timeout_s=1.0)
    assert "extract_timeout_s" in SimulatorValidator.identity_ignores  # a setting that changes no answer
    got = val.simulate_features(unit, sim, SleepyFeatures(limit=0.5))
    inline = val.__class__(batch_size=5).simulate_features(unit, sim, ToyFeatures())
    stuck = [r for r, f in enumerate(got.failures) if f and "extraction took longer than 1 s" in f]
    assert len(stuck) == 1 and inline.failures[stuck[0]] is None and np.isnan(got.features[stuck[0]]).all()
    for r in set(range(12)) - set(stuck):  # every other run as extracted in the simulator's thread
        assert got.failures[r] == inline.failures[r]
        np.testing.assert_array_equal(got.features[r], inline.features[r])


def test_workers_run_native_pools_on_the_threads_given():
    """Each worker's BLAS/OpenMP pools get ``threads`` threads (default one), not one per core of the host:
    six workers on a 16-core GPU host would otherwise start 96 threads and starve the simulator's process."""

    from invphys.core.threads import native_threads
    from invphys.plugins.executors._extract_pool import ExtractionPool

    with ExtractionPool({"type": FEATURES}, 1, min_shared_bytes=None) as pool:
        info = pool._pool.submit(native_threads).result()
    assert pool.threads == 1
    assert info["pools"] == [1] and info["env"]["OMP_NUM_THREADS"] == "1"
    with ExtractionPool({"type": FEATURES}, 1, min_shared_bytes=None, threads=2) as pool:
        assert pool._pool.submit(native_threads).result()["pools"] == [2]
    with pytest.raises(Exception, match="extraction threads"):
        ExtractionPool({"type": FEATURES}, 1, threads=0)
