"""The AnisoMPM engine's build phase and host-side rules (pure NumPy: no taichi, no warp)."""

from __future__ import annotations

import numpy as np
import pytest
from invphys_anisompm import (
    Box,
    Cylinder,
    EngineOptions,
    HalfSpace,
    MaterialSpec,
    SceneBuilder,
    SceneError,
    Sphere,
    Waypoints,
    lattice,
    linear_cut,
)
from invphys_anisompm.engine import estimated_substeps, frame_plan, kinematic_table, run_dt_bound
from invphys_anisompm.materials import critical_stress, lame
from invphys_anisompm.regions import Shell

DX = 0.01
OPTS = EngineOptions(dx=DX, grid=16, fps=50.0)


def test_lattice_spacing_and_membership() -> None:
    pts = lattice(Box((0.05, 0.05, 0.05), (0.09, 0.07, 0.06)), 0.005)
    assert len(pts) == 8 * 4 * 2
    assert np.allclose(np.diff(np.unique(pts[:, 0])), 0.005)
    with pytest.raises(ValueError, match="unbounded"):
        lattice(HalfSpace((0, 0, 0), (0, 1, 0)), 0.01)


def test_first_body_claims_shared_particles() -> None:
    """A skin added before the flesh it wraps takes the shell; together they tile the sphere once."""
    ball = Sphere((0.08, 0.08, 0.08), 0.03)
    b = SceneBuilder(OPTS)
    b.add_body("skin", Shell(ball, 0.008), MaterialSpec(fibre_ratio=2.0, fibre_alpha=-1.0),
               fibres=lambda p: np.tile([1.0, 0.0, 0.0], (len(p), 1)))
    b.add_body("flesh", ball)
    scene = b.build()
    alone = lattice(ball, OPTS.spacing)
    assert scene.n_particles == len(alone)
    assert scene.bodies[0].count + scene.bodies[1].count == len(alone)
    r = np.linalg.norm(scene.positions - 0.08, axis=1)
    assert r[scene.body_mask("skin")].min() >= 0.03 - 0.008 - 1e-12
    assert np.all(scene.fibres[scene.body_mask("flesh")] == 0)
    assert np.allclose(scene.fibres[scene.body_mask("skin")], [1, 0, 0])


def test_grips_colliders_held_and_errors() -> None:
    b = SceneBuilder(OPTS)
    b.add_body("block", Box((0.04, 0.03, 0.04), (0.1, 0.06, 0.1)))
    b.add_grip("tab", Box((0.09, 0.03, 0.04), (0.1, 0.06, 0.1)), linear_cut((1, 0, 0), 0.01, 0.1))
    b.add_collider("board", HalfSpace((0, 0.03, 0), (0, 1, 0)), surface="sticky")
    b.hold(Box((0.0, 0.0, 0.0), (0.05, 0.05, 0.16)))
    scene = b.build()
    assert scene.kinematic_names == ("tab", "board")
    assert (scene.grip == 0).sum() == scene.grips[0].count > 0
    assert scene.held.sum() == 6 * 6 * 16
    with pytest.raises(SceneError, match="unique"):
        b.add_body("block", Box((0, 0, 0), (1, 1, 1)))
    with pytest.raises(SceneError, match="surface"):
        b.add_collider("x", HalfSpace((0, 0, 0), (0, 1, 0)), surface="glue")
    with pytest.raises(SceneError, match="outside"):
        SceneBuilder(OPTS).add_body("big", Box((0.0, 0.0, 0.0), (0.1, 0.1, 0.1))).build()
    with pytest.raises(SceneError, match="no particles"):
        SceneBuilder(OPTS).add_body("a", Box((0.05,) * 3, (0.06,) * 3)).add_body("b", Box((0.05,) * 3, (0.06,) * 3)).build()


def test_critical_stress_makes_phi_one_at_the_stretch() -> None:
    """In a free tensile test at strain p the only positive principal stress equals sigma_c."""
    mu, lam = lame(np.array([1e4, 2e5]), np.array([0.3, 0.45]))
    p = np.array([0.1, 0.4])
    sc = critical_stress(p, mu, lam)
    assert np.all(sc > 0) and sc[1] > sc[0]
    # linear elasticity limit: sigma_c ~ E p for small p
    small = critical_stress(np.array([1e-4]), *lame(np.array([1e4]), np.array([0.3])))
    assert abs(small[0] / (1e4 * 1e-4) - 1) < 1e-2


def _wire_scene(eta: float = 0.1):
    b = SceneBuilder(EngineOptions(dx=DX, grid=16, fps=50.0, settle_seconds=0.1))
    b.add_body("block", Box((0.04, 0.03, 0.04), (0.1, 0.06, 0.1)), MaterialSpec(E=1e4, nu=0.3, rho=1000.0, eta=eta))
    b.add_collider("wire", Cylinder((0.07, 0.08, 0.07), 0.01), path=linear_cut((0, -1, 0), 0.04, 0.2, t_start=0.02))
    return b.build()


def test_dt_is_bounded_by_cfl_eta_and_the_collider() -> None:
    scene = _wire_scene()
    model = scene.model(3).set_material("block", E=[1e4, 1e6, 1e4], eta=[0.1, 0.1, 1e-4])
    dt = run_dt_bound(model, frames=20)
    c = model.wave_speed()
    assert dt[0] <= 0.4 * DX / c[0] + 1e-15
    assert dt[1] < dt[0]                                  # stiffer -> smaller dt
    assert dt[2] == pytest.approx(0.1 * 1e-4)             # eta bound binds
    assert np.all(dt <= 0.2 * DX / 0.2 + 1e-12)           # the wire moves 0.2 m/s: kinematic CFL
    nsub, step = frame_plan(50.0, dt)
    assert np.allclose(nsub * step, 1 / 50.0) and np.all(step <= dt)
    est = estimated_substeps(model, frames=20)
    assert est[1] > est[0] and est[2] == (20 + 5) * nsub[2]


def test_kinematic_table_follows_the_path_exactly() -> None:
    scene = _wire_scene()
    nsub = np.array([4, 8])
    dt = (1 / 50.0) / nsub
    table = kinematic_table(scene, frame=3, nsub=nsub, dt=dt, active=np.array([True, True]))
    assert table.shape == (2, 8, 1, 6)
    t_end = 4 / 50.0
    path = scene.colliders[0].path
    assert np.allclose(table[0, 3, 0, :3], path.displacement(t_end))
    assert np.allclose(table[1, 7, 0, :3], path.displacement(t_end))
    assert np.allclose(table[1, :, 0, 4], -0.2)           # mid-cut: constant downward speed
    w = Waypoints((0.0, 1.0), ((0, 0, 0), (1, 0, 0)), ease=0.2)
    assert np.allclose(w.displacement(0.5), [0.5, 0, 0]) and w.peak_speed(1.2) < 1.01
