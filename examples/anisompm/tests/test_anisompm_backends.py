"""The AnisoMPM engine's kernels on CPU: Taichi/Warp parity, batching, physics checks, failures.

A tiny scene with every engine feature (two bodies, one with fibres; a grip; a moving wire collider; a
sticky board; a held region; gravity with settling; damage): ~700 particles, 10 frames.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm import Box, Engine, EngineOptions, HalfSpace, MaterialSpec, SceneBuilder
from invphys_anisompm.testing import DX, FLOOR, build_scene, has_warp

SCENE = build_scene(settle_seconds=0.06)
MODEL = SCENE.model(2).set_material("paste", E=[3e4, 6e4], eta=[0.02, 0.05]).set_friction("wire", [0.3, 0.0])


@pytest.fixture(scope="module")
def runs() -> dict:
    return {be: Engine(SCENE, backend=be, arch="cpu").run(MODEL, frames=10, record_every=5)
            for be in ("taichi", "warp") if be == "taichi" or has_warp()}


def test_taichi_and_warp_agree_on_cpu(runs) -> None:
    """Same substeps; positions, damage and the wire force agree to float32 round-off."""
    if "warp" not in runs:
        pytest.skip("warp-lang is not installed")
    for rt, rw in zip(runs["taichi"], runs["warp"], strict=True):
        assert rt.ok and rw.ok
        assert rt.substeps == rw.substeps and rt.settle_substeps == rw.settle_substeps
        xt, xw = np.stack(rt.positions), np.stack(rw.positions)
        moved = np.abs(xt[-1] - xt[0]).max()
        assert moved > DX                                   # the wire and the grip really moved material
        assert np.abs(xt - xw).max() < 1e-4 * moved
        assert np.abs(np.stack(rt.damage) - np.stack(rw.damage)).max() < 1e-3
        assert float(np.stack(rt.damage).max()) > 0.05      # and it fractured: the comparison covers damage
        ft, fw = rt.series_array("force/wire"), rw.series_array("force/wire")
        assert np.abs(ft - fw).max() < 1e-3 * np.abs(ft).max()


def test_series_shapes_and_physics(runs) -> None:
    """Every per-frame series has frames + 1 entries; after settling the board carries the weight."""
    r = runs["taichi"][0]
    assert r.frames == [0, 5, 10]
    for name in ("max_speed", "centroid/rind", "mean_damage/paste", "force/wire", "work/tab", "position/wire"):
        assert len(r.series[name]) == 11, name
    weight = float(MODEL.total_mass()[0]) * 9.81
    board = r.series_array("force/board")[0]
    assert -weight < board[1] < -0.5 * weight              # the board carries what the grip and clamp do not
    wire = r.series_array("force/wire")
    assert abs(wire[0, 1]) < 0.01 * wire[:, 1].max()       # (almost) no contact at rest; pushed up once cutting
    assert r.series_array("work/wire")[-1] > 0             # the wire did work on the cheese
    assert np.allclose(r.series_array("position/wire")[-1], [0, -0.035, 0], atol=1e-9)
    stiffer = runs["taichi"][1]
    assert stiffer.series_array("force/wire")[:, 1].max() != wire[:, 1].max()


def test_batched_runs_equal_single_runs(runs) -> None:
    """A run gives the same trajectory alone and inside a batch (n_envs = 1 vs B)."""
    alone = Engine(SCENE, backend="taichi", arch="cpu").run(MODEL.take([1]), frames=10, record_every=5)[0]
    np.testing.assert_array_equal(np.stack(alone.positions), np.stack(runs["taichi"][1].positions))
    np.testing.assert_array_equal(alone.series_array("force/wire"), runs["taichi"][1].series_array("force/wire"))


def test_run_batched_restores_order() -> None:
    model = SCENE.model(3).set_material("paste", E=[9e5, 3e4, 6e4])
    seen = []
    recs = Engine(SCENE, backend="taichi", arch="cpu").run_batched(model, frames=2, record_every=2, batch_size=2,
                                                                  on_result=lambda i, r: seen.append(i))
    assert sorted(seen) == [0, 1, 2]
    assert recs[0].dt < recs[1].dt                         # stiffest first in model order, smallest dt


def test_blow_up_is_a_failure_not_data() -> None:
    """A violated CFL (cfl = 10) fails with a categorised reason on both backends."""
    scene = dataclasses.replace(SCENE, options=dataclasses.replace(SCENE.options, cfl=10.0, velocity_cfl=10.0,
                                                                   min_substeps_per_frame=1))
    model = scene.model(1).set_material("paste", E=[5e6]).set_material("rind", E=[5e6])
    for be in ("taichi", "warp") if has_warp() else ("taichi",):
        rec = Engine(scene, backend=be, arch="cpu").run(model, frames=6, record_every=3)[0]
        assert not rec.ok and rec.positions == []
        assert rec.failure.split(":")[0] in {"nan", "domain", "energy", "dt"}, rec.failure


def test_settled_block_weighs_on_the_board() -> None:
    """Gravity and settling: a free block at rest pushes the board down with its weight (to 3%)."""
    b = SceneBuilder(EngineOptions(dx=DX, grid=16, fps=50.0, gravity=-9.81, settle_seconds=0.2))
    b.add_body("block", Box((0.04, FLOOR, 0.04), (0.088, FLOOR + 0.032, 0.072)), MaterialSpec(E=5e4, rho=1000.0))
    b.add_collider("board", HalfSpace((0, FLOOR, 0), (0, 1, 0)), surface="sticky")
    scene = b.build()
    model = scene.model(1)
    rec = Engine(scene, backend="taichi", arch="cpu").run(model, frames=2, record_every=2)[0]
    weight = float(model.total_mass()[0]) * 9.81
    assert rec.series_array("force/board")[:, 1] == pytest.approx(-weight, rel=0.03)
    sag = rec.series_array("centroid/block")[0, 1] - scene.positions[:, 1].mean()
    assert -0.05 * DX < sag < 0                                # it settled down a little, elastically
