"""Continuous batching (``Engine.stream``) against the lock-step path, on CPU with both backends.

A tiny scene with every engine feature (fibres, a grip, a moving wire, a sticky board, a held region,
settling, damage, host reductions); runs of different stiffness and damage rate have different
substeps per frame, so slots reach their frame ends at different times and get refilled mid-batch.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm import Engine
from invphys_anisompm.testing import build_scene, has_warp

FRAMES = 6

SCENE = build_scene(settle_seconds=0.04,
                    reductions={"low_damage": lambda x, d, scene: (d < 0.5).mean(axis=1)})
E = [3e4, 2e5, 6e4, 9e5, 1e5]
MODEL = SCENE.model(len(E)).set_material("paste", E=E, eta=[0.02, 0.05, 0.01, 0.03, 0.02]) \
    .set_friction("wire", [0.3, 0.0, 0.1, 0.2, 0.3])


def _backends() -> list[str]:
    return ["taichi", "warp"] if has_warp() else ["taichi"]


@pytest.mark.parametrize("backend", _backends())
def test_stream_equals_lockstep(backend: str) -> None:
    engine = Engine(SCENE, backend=backend, arch="cpu")
    plain = engine.run(MODEL, frames=FRAMES, record_every=3)
    assert len({r.substeps for r in plain}) > 2, "runs must differ in cost for the test to mean anything"
    got = dict(engine.stream(MODEL, frames=FRAMES, record_every=3, batch_size=2))
    assert sorted(got) == list(range(len(E)))
    for i, ref in enumerate(plain):
        rec = got[i]
        assert rec.failure == ref.failure
        assert (rec.substeps, rec.settle_substeps, rec.guard_frames, rec.frames) == \
            (ref.substeps, ref.settle_substeps, ref.guard_frames, ref.frames)
        for a, b in zip(rec.positions + rec.damage, ref.positions + ref.damage, strict=True):
            np.testing.assert_array_equal(a, b)   # bit-identical particle states
        assert set(rec.series) == set(ref.series)
        for name in ref.series:   # force/work sums too: a slot's sums are read once per frame, as in lock-step
            np.testing.assert_array_equal(rec.series_array(name), ref.series_array(name), err_msg=name)


def test_a_stream_whose_particle_reads_finish_later_equals_lockstep() -> None:
    """Taichi's ``read_slots_later`` on the CUDA path (driver calls emulated on the CPU: a copy happens only when
    waited for, so a gather that overwrote its buffers before the read was taken would show): records bit for bit
    the lock-step ones, and the reads did go through the later copies."""
    from fake_cuda_copies import fake_later_copies

    engine = Engine(SCENE, backend="taichi", arch="cpu")
    plain = engine.run(MODEL, frames=FRAMES, record_every=3)
    be = engine.backend(2)
    be.later, fake = fake_later_copies(be.host_copy, capacity=2 * SCENE.n_particles * 16)
    got = dict(engine.stream(MODEL, frames=FRAMES, record_every=3, batch_size=2))
    assert be.later.fallback is None and fake.calls.count("copy") >= 2 * len(E)
    for i, ref in enumerate(plain):
        rec = got[i]
        assert rec.frames == ref.frames and len(rec.positions) == len(ref.positions) > 0
        for a, b in zip(rec.positions + rec.damage, ref.positions + ref.damage, strict=True):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(rec.series_array("low_damage"), ref.series_array("low_damage"))


def test_stream_idles_only_in_the_tail_and_reuses_the_backend() -> None:
    engine = Engine(SCENE, backend="taichi", arch="cpu")
    out = dict(engine.stream(MODEL, frames=FRAMES, record_every=3, batch_size=2))
    c = engine.counters
    per_run = [r.substeps + r.settle_substeps for r in out.values()]
    assert c.useful == sum(per_run)
    # slots only idle once the queue is empty: at most (B - 1) slots for the last run's length
    assert 0 <= c.launched - c.useful <= (2 - 1) * max(per_run)
    n_backends = len(engine._backends)
    # a second stream on the same engine reuses the allocated slots (a warm engine)
    again = dict(engine.stream(MODEL.take(np.array([3, 1])), frames=FRAMES, record_every=3, batch_size=2))
    assert len(engine._backends) == n_backends and sorted(again) == [0, 1]
    np.testing.assert_array_equal(again[0].positions[-1], out[3].positions[-1])


def test_a_live_stream_holds_its_slots_until_it_ends() -> None:
    from invphys_anisompm import EngineBusyError

    engine = Engine(SCENE, backend="taichi", arch="cpu")
    first = engine.stream(MODEL, frames=FRAMES, record_every=3, batch_size=2)
    i, rec = next(first)                          # suspended at a yield, its two slots mid-run
    with pytest.raises(EngineBusyError, match="2-slot backend is serving a stream"):
        next(engine.stream(MODEL, frames=FRAMES, record_every=3, batch_size=2))
    with pytest.raises(EngineBusyError):
        engine.run(MODEL.take(np.array([0, 1])), frames=FRAMES, record_every=3)
    other = dict(engine.stream(MODEL.take(np.array([2, 4, 0])), frames=FRAMES, record_every=3, batch_size=3))
    assert sorted(other) == [0, 1, 2]              # another slot count is another backend: free
    rest = dict(first)                             # the first stream, undisturbed, finishes
    assert sorted([i, *rest]) == list(range(len(E)))
    plain = engine.run(MODEL, frames=FRAMES, record_every=3)   # slots free again
    for j, r in {i: rec, **rest}.items():
        np.testing.assert_array_equal(r.positions[-1], plain[j].positions[-1])
    closed = engine.stream(MODEL, frames=FRAMES, record_every=3, batch_size=2)
    next(closed)
    closed.close()                                 # a closed stream gives its slots back too
    assert len(dict(engine.stream(MODEL.take(np.array([1])), frames=FRAMES, record_every=3, batch_size=2))) == 1


def test_finished_runs_are_handed_out_while_the_next_chunk_runs() -> None:
    """A finished run is yielded after the next chunk is launched (on a GPU the launch is asynchronous, so
    the caller's work on the run overlaps the kernels), and the kinematic tables of a slot's next frame are
    built before that frame ends (they are found in the cache when the frame starts)."""
    import invphys_anisompm.streaming as streaming

    engine = Engine(SCENE, backend="taichi", arch="cpu")
    backend = engine.backend(2)
    calls = {"advance": 0, "frame_end": 0, "table_after_frame_end": 0}
    advance, frame_end, table = backend.advance, backend.frame_end, streaming.kinematic_table
    in_frame_end = {"now": False}

    def spy_advance(n: int) -> None:
        calls["advance"] += 1
        in_frame_end["now"] = False
        advance(n)

    def spy_frame_end(*args):
        calls["frame_end"] += 1
        in_frame_end["now"] = True
        return frame_end(*args)

    def spy_table(*args, **kwargs):
        calls["table_after_frame_end"] += in_frame_end["now"]
        return table(*args, **kwargs)

    backend.advance, backend.frame_end = spy_advance, spy_frame_end
    streaming.kinematic_table = spy_table
    try:
        at_yield = [(calls["advance"], calls["frame_end"])
                    for _ in engine.stream(MODEL, frames=FRAMES, record_every=3, batch_size=2)]
    finally:
        streaming.kinematic_table = table
    assert len(at_yield) == len(E)
    # every run but the last two (finished when no slot has work left) is yielded with a chunk in flight
    assert sum(a == f + 1 for a, f in at_yield) >= len(E) - 2
    assert all(a in (f, f + 1) for a, f in at_yield)
    # tables are built between a chunk's launch and its frame end, not while the GPU waits for the next
    # chunk: only the velocity guard raising a frame's substeps could need one after a frame end
    assert calls["table_after_frame_end"] == 0


def test_failed_run_frees_its_slot() -> None:
    import dataclasses

    bad_model = SCENE.model(3).set_material("paste", E=[3e4, 6e4, 9e4])
    strict = dataclasses.replace(SCENE.options, max_substeps_per_frame=1)
    eng = Engine(dataclasses.replace(SCENE, options=strict), backend="taichi", arch="cpu")
    out = dict(eng.stream(bad_model, frames=2, record_every=1, batch_size=1))
    assert sorted(out) == [0, 1, 2]
    assert all(r.failure and r.failure.startswith("dt:") and r.positions == [] for r in out.values())


@pytest.mark.parametrize("settle_seconds", [0.0, 0.04])
def test_failures_keep_their_reasons_and_no_particle_frames(settle_seconds: float) -> None:
    """A run failing at a frame end (``energy``) or at a frame start (``dt``, right after the first frame was
    taken when nothing settles) ends as in lock-step: the same reason, no particle frames."""
    import dataclasses

    scene = build_scene(settle_seconds=settle_seconds)
    model = scene.model(3).set_material("paste", E=[3e4, 6e4, 9e4])
    for change in ({"energy_factor": 1e-30}, {"max_substeps_per_frame": 1}):
        strict = dataclasses.replace(scene, options=dataclasses.replace(scene.options, **change))
        engine = Engine(strict, backend="taichi", arch="cpu")
        plain = engine.run(model, frames=2, record_every=1)
        out = dict(engine.stream(model, frames=2, record_every=1, batch_size=2))
        assert all(r.failure for r in plain), change
        for i, ref in enumerate(plain):
            assert out[i].failure == ref.failure
            assert out[i].positions == [] == ref.positions and out[i].damage == []


def test_frame_statistics_in_partial_rows_agree_with_the_plain_sums() -> None:
    """The GPU's layout of the frame statistics (particles spread over partial rows, then reduced) run on
    the CPU: same particles bit for bit (the peak speed, which drives the velocity guard, is a max), the
    series to float32 summation-order round-off."""
    plain = Engine(SCENE, backend="taichi", arch="cpu").run(MODEL, frames=FRAMES, record_every=3)
    spread = dict(Engine(SCENE, backend="taichi", arch="cpu", stats_partials=7)
                  .stream(MODEL, frames=FRAMES, record_every=3, batch_size=2))
    for i, ref in enumerate(plain):
        rec = spread[i]
        assert rec.substeps == ref.substeps and rec.guard_frames == ref.guard_frames
        np.testing.assert_array_equal(rec.positions[-1], ref.positions[-1])
        np.testing.assert_array_equal(rec.series_array("max_speed"), ref.series_array("max_speed"))
        for name in ("kinetic_energy", "centroid/paste", "mean_damage/paste"):
            want = ref.series_array(name)
            np.testing.assert_allclose(rec.series_array(name), want, rtol=1e-5,
                                       atol=1e-6 * float(np.abs(want).max()) + 1e-12, err_msg=name)


def _grid_channels(be) -> list[np.ndarray]:
    """The backend's grid arrays as host copies: velocity/momentum, mass, damage sums, grip mass."""
    return [a.numpy().copy() if hasattr(a, "numpy") else a.to_numpy() for a in (be.gv, be.gm, be.gd, be.gg)]


def _set_grid(be, channels: list[np.ndarray]) -> None:
    for arr, values in zip((be.gv, be.gm, be.gd, be.gg), channels, strict=True):
        if hasattr(arr, "assign"):
            arr.assign(values)
        else:
            arr.from_numpy(values)


@pytest.mark.parametrize("backend", _backends())
def test_the_clear_skips_untouched_nodes_and_a_new_run_gets_a_clean_grid(backend: str) -> None:
    """The substep's clear zeroes only the nodes the last scatter touched (weight sum nonzero); whatever a
    run left elsewhere (a NaN beside a zero weight, if it blew up) must not reach the next run in its slot,
    through ``load`` or ``load_slots``."""
    B, steps = 2, 6
    model = SCENE.model(B).set_material("paste", E=[3e4, 9e4])
    nk = max(len(SCENE.kinematic_names), 1)

    def frame(be) -> None:
        be.set_frame(np.full(B, 1e-4), np.full(B, steps), np.zeros((B, steps, nk, 6)), damage_on=True)
        be.advance(steps)

    clean = Engine(SCENE, backend=backend, arch="cpu").backend(B)
    clean.load(model.table(), model.friction)
    frame(clean)
    want = clean.read()

    def after_reload(reload) -> tuple[np.ndarray, np.ndarray]:
        be = Engine(SCENE, backend=backend, arch="cpu").backend(B)
        be.load(model.table(), model.friction)
        frame(be)
        # what a blown-up run can leave: NaN momentum on nodes whose weight sum is zero, where the next
        # run's particles land (here: everywhere), which the substep's clear does not look at
        gv, gm, gd, gg = _grid_channels(be)
        _set_grid(be, [np.full_like(gv, np.nan), np.zeros_like(gm), np.zeros_like(gd), np.zeros_like(gg)])
        reload(be)
        frame(be)
        return be.read()

    for reload in (lambda be: be.load(model.table(), model.friction),
                   lambda be: be.load_slots(np.arange(B), model.table(), model.friction)):
        x, d = after_reload(reload)
        assert np.isfinite(x).all()
        np.testing.assert_array_equal(x, want[0])
        np.testing.assert_array_equal(d, want[1])
    # the clear itself: after a substep, the untouched nodes are exactly zero in every channel
    gv, gm, gd, gg = _grid_channels(clean)
    untouched = gd[..., 1] == 0.0
    assert not gv[untouched].any() and not gm[untouched].any() and not gg[:B][untouched].any()


def test_one_run_velocity_guard_equals_the_batched_one_bit_for_bit():
    from invphys_anisompm.engine import velocity_guard, velocity_guard_one

    rng = np.random.default_rng(0)
    vmax = np.concatenate([rng.lognormal(0.0, 3.0, 2000), [0.0, 1e-30, 1e-300, 5e-324, np.nan, np.inf, 1e300, 1e17]])
    nsub = rng.integers(1, 400, len(vmax))
    for dx, fps, cfl in ((0.01, 30.0, 0.3), (0.0037, 24.0, 0.5)):
        with np.errstate(all="ignore"):   # the batched guard's casts of the absurd speeds warn
            batched = velocity_guard(nsub, vmax, dx, fps, cfl)
        one = [velocity_guard_one(int(n), float(v), dx, fps, cfl) for n, v in zip(nsub, vmax, strict=True)]
        assert np.array_equal(batched, np.array(one)), (dx, fps, cfl)
    assert np.count_nonzero(batched > nsub) > 100     # the guard binds often enough for the check to mean something


def test_unhealthy_flags_the_rows_frame_failure_fails():
    from invphys_anisompm.failure import (
        STAT_KE,
        STAT_NONFINITE,
        STAT_OUTSIDE,
        frame_failure,
        n_stats,
        unhealthy,
    )

    rng = np.random.default_rng(1)
    n = 4000
    stats = rng.normal(0.0, 1.0, (n, n_stats(2)))
    stats[:, STAT_NONFINITE] = rng.random(n) < 0.05
    stats[:, STAT_OUTSIDE] = (rng.random(n) < 0.05) * rng.integers(1, 9, n)
    stats[:, STAT_KE] = rng.lognormal(0.0, 2.0, n)
    for col, value in ((STAT_KE, np.nan), (5, np.inf), (7, -np.inf), (STAT_KE, np.inf)):
        stats[rng.random(n) < 0.02, col] = value
    bound = rng.lognormal(1.0, 1.0, n)
    extra = np.where(rng.random(n) < 0.03, np.nan, rng.normal(size=n))
    want = np.array([frame_failure(stats[i], float(bound[i]), 3, float(extra[i])) is not None for i in range(n)])
    assert np.array_equal(unhealthy(stats, bound, extra), want)
    assert 0.2 < want.mean() < 0.8   # healthy and failing rows, each reason among them


def test_a_function_path_evaluates_its_origin_once_and_moves_as_before():
    from invphys_anisompm.paths import FunctionPath

    calls = []

    def fn(t):
        calls.append(np.shape(t))
        t = np.asarray(t, float)
        return np.stack([np.sin(t) + 2.0, t * t, np.ones_like(t)], axis=-1)

    path = FunctionPath(fn)
    ts = np.linspace(0.0, 3.0, 7)
    first, second = path.displacement(ts), path.displacement(ts[::-1])
    want = fn(ts) - fn(np.zeros(()))
    assert np.array_equal(first, want) and np.array_equal(second, want[::-1])
    assert calls.count(()) == 1 + 1                     # fn(0) once for the path, once for `want` above
    assert path == FunctionPath(fn)                     # the cache is not a field


@pytest.mark.parametrize("per_feed", [1, 3])
def test_an_open_stream_fed_as_results_come_equals_lockstep(per_feed: int) -> None:
    """``Engine.stream_feed``: runs handed in while others are in flight (the next ones only once a result came
    back, as a refine asks its next generation) get the lock-step records bit for bit, numbered in feed order."""
    engine = Engine(SCENE, backend="taichi", arch="cpu")
    plain = engine.run(MODEL, frames=FRAMES, record_every=3)
    order = [3, 0, 4, 1, 2]
    fed: list[int] = []
    ready = order[:per_feed]
    polls = []

    def feeder(free: int):
        polls.append(free)
        if not ready:
            return None
        take = ready[:]
        ready.clear()
        fed.extend(take)
        return MODEL.take(np.array(take))

    got = {}
    for i, rec in engine.stream_feed(feeder, frames=FRAMES, record_every=3, batch_size=2):
        got[fed[i]] = rec
        nxt = order[len(fed) + len(ready):][:per_feed]   # a result back: the next runs become ready
        ready.extend(nxt)
    assert sorted(got) == list(range(len(E))) and fed == order
    assert max(polls) <= 2   # never asked for more runs than free slots
    for i, ref in enumerate(plain):
        rec = got[i]
        assert (rec.failure, rec.substeps, rec.frames) == (ref.failure, ref.substeps, ref.frames)
        for a, b in zip(rec.positions + rec.damage, ref.positions + ref.damage, strict=True):
            np.testing.assert_array_equal(a, b)
        for name in ref.series:
            np.testing.assert_array_equal(rec.series_array(name), ref.series_array(name), err_msg=name)
    assert not engine._streaming   # the slots are free again
    assert list(engine.stream_feed(lambda free: None, frames=FRAMES, record_every=3, batch_size=2)) == []
