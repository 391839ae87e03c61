"""The ``ray_actors`` executor on real Ray with CPU actors: warm actors (one plugin build each, the same
process for every chunk), dynamic chunks spread over the actors, the same rows as the local executor
(toy oscillators, batched and with a stream of their own), per-row failures when a
row raises or kills its actor, and one-line errors (exit 2) without Ray or without GPUs."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest
from test_dataset_toy import FEATURES, SIM, STREAMING, ToyOscillator
from typer.testing import CliRunner

from invphys import registry
from invphys.cli import app
from invphys.core.dataset import DatasetStore
from invphys.core.errors import InvphysError
from invphys.data.generate import generate_dataset
from invphys.plugins.executors import LocalExecutor, RayActorsExecutor

TESTS = str(Path(__file__).resolve().parent)
SPEC = f"""\
name: ray-actors-cli
simulator: {{type: "{SIM}", substeps: 1}}
features: {{type: "{FEATURES}"}}
executor: {{type: ray_actors}}
dataset: {{n: 4, batch_size: 2}}
"""


def _params(n: int, seed: int = 3) -> np.ndarray:
    space = ToyOscillator().parameter_space()
    return space.denormalize(np.random.default_rng(seed).random((n, space.dim)))


def _collect(executor, sim: dict, feats: dict, params: np.ndarray, batch_size: int) -> dict[int, object]:
    out = {}
    for i, res in executor.run(sim, feats, params, batch_size):
        assert i not in out, "a row was yielded twice"
        out[i] = res
    assert sorted(out) == list(range(len(params)))
    return out


def test_registered_and_clear_errors_without_ray_or_gpus(tmp_path, monkeypatch) -> None:
    assert registry.get("executor", "ray_actors") is RayActorsExecutor
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC)
    runner = CliRunner()
    with monkeypatch.context() as m:   # Ray not installed: one line, exit 2
        m.setitem(sys.modules, "ray", None)
        res = runner.invoke(app, ["dataset", "generate", str(spec), "--out", str(tmp_path / "a")])
        assert res.exit_code == 2, res.output
        assert "'ray_actors' executor needs Ray" in res.output and "invphys[ray]" in res.output
        assert "Traceback" not in res.output
        with pytest.raises(InvphysError, match="'ray' executor needs Ray"):
            next(registry.create("executor", {"type": "ray"}).run({"type": SIM}, None, _params(2), 1))


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    # local Ray workers inherit the driver's environment: make the toy plugin importable there
    old = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join([TESTS, old or ""])
    ray.init(num_cpus=2, num_gpus=0, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        yield ray
    finally:
        ray.shutdown()
        if old is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = old


def test_gpu_actors_without_gpus_is_one_clear_error(ray_instance, tmp_path) -> None:
    with pytest.raises(InvphysError, match=r"asks for 1 GPU per actor but the local Ray instance sees 0 GPUs"):
        list(RayActorsExecutor().run({"type": SIM}, None, _params(2), 1))
    with pytest.raises(InvphysError, match=r"3 actors x 1 CPUs need 3 CPUs"):
        list(RayActorsExecutor(num_gpus=0, actors=3).run({"type": SIM}, None, _params(2), 1))
    spec = tmp_path / "spec.yaml"
    spec.write_text(SPEC)   # default num_gpus 1 through the CLI: exit 2, one line
    res = CliRunner().invoke(app, ["dataset", "generate", str(spec), "--out", str(tmp_path / "b")])
    assert res.exit_code == 2 and "sees 0 GPUs (set num_gpus: 0 for CPU actors)" in res.output, res.output
    assert ray_instance.is_initialized()   # an instance the executor did not start is left alone


def test_warm_cpu_actors_match_local_and_isolate_failures(ray_instance, tmp_path) -> None:
    sim = {"type": SIM, "substeps": 1, "raise_c_above": 0.6, "sleep_s": 0.02}
    feats = {"type": FEATURES}
    params = _params(24)
    local = _collect(LocalExecutor(), sim, feats, params, batch_size=3)
    ex = RayActorsExecutor(num_gpus=0, actors=2, keep_actors=True)
    try:
        got = _collect(ex, sim, feats, params, batch_size=3)
        first = ex.actor_info()
        again = _collect(ex, sim, feats, params[:6], batch_size=3)   # same warm actors, no rebuild
        info = ex.actor_info()
        assert ex.apply(_substeps_of, sim, feats) == [1, 1]
        ex.config.actors = 1   # a smaller pool later: the first warm actor takes every chunk
        _collect(ex, sim, feats, params[:6], batch_size=3)
        one = ex.actor_info()
    finally:
        ex.close()
    for i in local:
        assert got[i].ok == local[i].ok and got[i].failure == local[i].failure
        if local[i].ok:
            np.testing.assert_array_equal(got[i].features, local[i].features)
            np.testing.assert_array_equal(again.get(i, got[i]).features, local[i].features)
        assert got[i].trajectory is None
    raised = params[:, 1] > 0.6
    assert raised.any() and all(got[i].failure.startswith("RuntimeError: toy oscillator exploded")
                                for i in np.flatnonzero(raised))
    assert len(info) == 2 and len({d["pid"] for d in info}) == 2
    assert [d["pid"] for d in info] == [d["pid"] for d in first]
    assert all(d["builds"] == 1 for d in info)            # one simulator build per actor, for 10 chunks
    assert sum(d["chunks"] for d in first) == 8 and all(d["chunks"] >= 1 for d in first)   # both pulled
    assert sum(d["rows"] for d in info) == 30
    assert one[0]["chunks"] == info[0]["chunks"] + 2 and one[1]["chunks"] == info[1]["chunks"]


def _substeps_of(simulator, extractor) -> int:
    return simulator.config.substeps


def test_an_actor_that_dies_fails_only_its_row_and_generation_stores(ray_instance, tmp_path) -> None:
    crash = {"type": SIM, "substeps": 8, "crash_c_above": 0.8}
    params = _params(12, seed=5)[:6]
    crashing = params[:, 1] > 0.8
    assert crashing.sum() == 1
    got = _collect(RayActorsExecutor(num_gpus=0, actors=2, max_restarts=3), crash, {"type": FEATURES},
                   params, batch_size=3)
    for i, res in got.items():
        assert res.ok != crashing[i], res.failure
        if crashing[i]:
            assert res.failure.startswith("ray actor died")
    summary = generate_dataset(tmp_path / "ds", {"type": SIM, "substeps": 1}, n=8, batch_size=2,
                               executor={"type": "ray_actors", "num_gpus": 0, "actors": 2}, progress=False)
    assert summary.ran == 8 and summary.ok + summary.failed == 8
    assert len(DatasetStore(tmp_path / "ds").frame()) == 8


def _streaming(n: int, seed: int) -> tuple[np.ndarray, dict, dict]:
    """``n`` random parameter vectors and the blocks of the toy with a stream of its own (``native_stream``)."""
    return _params(n, seed), {"type": STREAMING, "substeps": 8}, {"type": FEATURES}


def test_a_native_stream_on_two_actors_matches_local(ray_instance) -> None:
    """Each actor streams its chunk through its warm simulator (the slot counters count every run's
    substeps), one build per actor, and the rows are the local executor's."""
    params, sim, feats = _streaming(6, seed=1)
    local = dict(LocalExecutor().run(sim, feats, params, batch_size=3))
    ex = RayActorsExecutor(num_gpus=0, actors=2, chunk_size=3, keep_actors=True)
    try:
        got = _collect(ex, sim, feats, params, batch_size=6)
        info = ex.actor_info()
    finally:
        ex.close()
    assert [d["chunks"] for d in info] == [1, 1] and all(d["builds"] == 1 for d in info)
    assert sum(d["useful_slot_substeps"] for d in info) == sum(got[i].stats.substeps for i in range(6))
    for i in range(6):
        assert got[i].ok == local[i].ok and got[i].failure == local[i].failure
        if local[i].ok:
            np.testing.assert_array_equal(got[i].features, local[i].features)


def test_actors_extract_in_worker_processes_with_the_same_features(ray_instance) -> None:
    """``extract_workers``: each actor extracts in its own warm processes (one pool per extractor spec, kept
    across chunks) while its simulator streams on; features equal the in-actor extraction's."""
    params, sim, feats = _streaming(4, seed=2)
    local = dict(LocalExecutor().run(sim, feats, params, batch_size=4))
    ex = RayActorsExecutor(num_gpus=0, actors=1, chunk_size=2, extract_workers=1, keep_actors=True)
    try:
        got = _collect(ex, sim, feats, params, batch_size=4)
        info = ex.actor_info()
    finally:
        ex.close()
    assert info[0]["chunks"] == 2 and info[0]["extract_workers"] == 1 and info[0]["extraction_pools"] == 1
    for i in range(4):
        assert got[i].ok == local[i].ok and got[i].trajectory is None
        if local[i].ok:
            np.testing.assert_array_equal(got[i].features, local[i].features)



class _StubRay:
    """Just enough of ``ray`` for ``_run``: refs complete in the order they were submitted."""

    def wait(self, refs: list, num_returns: int = 1, timeout: float | None = None) -> tuple[list, list]:
        return refs[:1], refs[1:]

    def get(self, ref):
        return ref()

    def cancel(self, ref) -> None:
        pass


class _StubActor:
    """A local :class:`SimulatorActor` whose next calls (``run`` or ``ping``) raise the scripted errors."""

    def __init__(self, errors: list[Exception]) -> None:
        from invphys.plugins.executors import _deadline
        from invphys.plugins.executors.ray_actors import SimulatorActor

        disposable = _deadline.DISPOSABLE
        self.actor, self.errors, self.calls = SimulatorActor({}), list(errors), []
        _deadline.DISPOSABLE = disposable  # an actor marks its process disposable; this one is the test's own
        self.run, self.ping = self._method("run"), self._method("ping")

    def _method(self, name: str):
        stub = self

        class Method:
            def remote(self, *args):
                stub.calls.append(name)
                error = stub.errors.pop(0) if stub.errors else None

                def ref():
                    if error is not None:
                        raise error
                    return getattr(stub.actor, name)(*args)
                return ref
        return Method()


def test_an_actor_that_died_gets_no_rows_until_it_answers_a_ping() -> None:
    from ray.exceptions import ActorUnavailableError, RayActorError

    sim, feats = {"type": SIM, "substeps": 1}, {"type": FEATURES}
    params = _params(6, seed=5)
    local = dict(LocalExecutor().run(sim, feats, params, batch_size=3))
    restarting = ActorUnavailableError("restarting", None)
    # the first chunk kills the actor; Ray is still restarting it at the first two pings
    actor = _StubActor([RayActorError(), restarting, restarting])
    executor = RayActorsExecutor(num_gpus=0, actors=1, max_restarts=3)
    executor._ray = _StubRay()
    got = dict(executor._run([actor], sim, feats, params, 3))
    assert sorted(got) == list(range(6))
    for i, res in got.items():   # as the local executor: no row failed for the actor's restart
        assert res.failure == local[i].failure
        assert res.ok == local[i].ok and (not res.ok or np.array_equal(res.features, local[i].features))
    assert actor.calls == ["run", "ping", "ping", "ping", "run", "run", "run", "run"]
    # an actor that stays unavailable counts as dead after `unavailable_retries` pings
    actor = _StubActor([RayActorError()] + [restarting] * 3)
    executor = RayActorsExecutor(num_gpus=0, actors=1, max_restarts=3, unavailable_retries=2)
    executor._ray = _StubRay()
    got = dict(executor._run([actor], sim, feats, params, 3))
    assert actor.calls == ["run", "ping", "ping", "ping"]
    assert all("did not come back after 2 pings" in res.failure for res in got.values())
