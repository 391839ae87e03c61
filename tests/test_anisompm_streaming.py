"""Continuous batching (``Engine.stream``) against the lock-step path, on CPU with both backends.

A tiny scene with every engine feature (fibres, a grip, a moving wire, a sticky board, a held region,
settling, damage, host reductions); runs of different stiffness and damage rate have different
substeps per frame, so slots reach their frame ends at different times and get refilled mid-batch.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm import (
    Box,
    Cylinder,
    Engine,
    EngineOptions,
    HalfSpace,
    MaterialSpec,
    SceneBuilder,
    linear_cut,
)

DX = 0.008
FLOOR = 3 * DX
FRAMES = 6


def build():
    opts = EngineOptions(dx=DX, grid=16, fps=50.0, gravity=-9.81, settle_seconds=0.04)
    b = SceneBuilder(opts)
    b.add_body("rind", Box((0.04, FLOOR + 0.032, 0.04), (0.088, FLOOR + 0.04, 0.072)),
               MaterialSpec(E=8e4, nu=0.3, rho=1000.0, fracture_stretch=0.1, eta=0.02, fibre_ratio=3.0,
                            fibre_alpha=-1.0),
               fibres=lambda p: np.tile([1.0, 0.0, 0.0], (len(p), 1)))
    b.add_body("paste", Box((0.04, FLOOR, 0.04), (0.088, FLOOR + 0.04, 0.072)),
               MaterialSpec(E=3e4, nu=0.3, rho=1100.0, fracture_stretch=0.08, eta=0.02))
    b.add_collider("board", HalfSpace((0, FLOOR, 0), (0, 1, 0)), surface="sticky")
    b.add_collider("wire", Cylinder((0.064, FLOOR + 0.05, 0.056), 0.006, axis=2, half_length=0.1),
                   friction=0.3, path=linear_cut((0, -1, 0), 0.035, 0.25, t_start=0.02))
    b.add_grip("tab", Box((0.04, FLOOR + 0.016, 0.04), (0.045, FLOOR + 0.04, 0.072)),
               linear_cut((-1, 0, 0), 0.01, 0.1), bodies=("paste",))
    b.hold(Box((0.08, 0.0, 0.0), (0.2, FLOOR + 0.012, 0.2)))
    b.add_reduction("low_damage", lambda x, d, scene: (d < 0.5).mean(axis=1))
    return b.build()


SCENE = build()
E = [3e4, 2e5, 6e4, 9e5, 1e5]
MODEL = SCENE.model(len(E)).set_material("paste", E=E, eta=[0.02, 0.05, 0.01, 0.03, 0.02]) \
    .set_friction("wire", [0.3, 0.0, 0.1, 0.2, 0.3])


def _backends() -> list[str]:
    try:
        import warp  # noqa: F401
    except ImportError:
        return ["taichi"]
    return ["taichi", "warp"]


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
        for name in ref.series:   # force/work sums: float32 device sums per chunk vs per frame
            want = ref.series_array(name)
            np.testing.assert_allclose(rec.series_array(name), want, rtol=1e-5,
                                       atol=1e-5 * float(np.abs(want).max()) + 1e-12, err_msg=name)


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


def test_failed_run_frees_its_slot() -> None:
    import dataclasses

    bad_model = SCENE.model(3).set_material("paste", E=[3e4, 6e4, 9e4])
    strict = dataclasses.replace(SCENE.options, max_substeps_per_frame=1)
    eng = Engine(dataclasses.replace(SCENE, options=strict), backend="taichi", arch="cpu")
    out = dict(eng.stream(bad_model, frames=2, record_every=1, batch_size=1))
    assert sorted(out) == [0, 1, 2]
    assert all(r.failure and r.failure.startswith("dt:") and r.positions == [] for r in out.values())
