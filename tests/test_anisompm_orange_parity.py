"""The orange peel rebuilt as an engine scene reproduces OrangePeelSimulator (Taichi, CPU, tiny preset).

The groundwork of porting the orange peel onto the engine: the orange's own particles, fibres, gripper
arc, held core, gravity, settling and dt rule, expressed with the engine's scene API only (the orange's
package is only read), give the same substeps and the same particle positions to float32 round-off.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")
pytest.importorskip("invphys_orange_peel")

from invphys_anisompm import Engine, EngineOptions, FunctionPath, MaterialSpec, SceneBuilder
from invphys_anisompm.regions import PointSet
from invphys_orange_peel.material import DENSITY_UNIT, POISSON
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.simulator import OrangePeelSimulator

FRAMES = 6


def orange_on_the_engine(sim: OrangePeelSimulator):
    sc, st, p = sim.scene, sim.step_settings(), sim.preset
    opts = EngineOptions(dx=sc.dx, grid=p.grid, fps=p.fps, gravity=st.gravity, settle_seconds=st.settle_seconds,
                         cfl=st.cfl, velocity_cfl=st.velocity_cfl, min_substeps_per_frame=st.min_substeps_per_frame,
                         max_substeps_per_frame=st.max_substeps_per_frame, eta_dt_factor=st.eta_dt_factor,
                         kinematic_cfl=1e9, apic_blend=st.apic_blend, l0_cells=st.l0_cells,
                         boundary_cells=st.boundary_cells, energy_factor=st.energy_factor)
    b = SceneBuilder(opts)
    skin, inner = sc.labels == 0, sc.labels == 1
    b.add_particles("skin", sc.positions[skin], MaterialSpec(nu=POISSON, fibre_alpha=-1.0), fibres=sc.fibres[skin],
                    volume=sc.volume)
    b.add_particles("interior", sc.positions[inner], MaterialSpec(nu=POISSON), volume=sc.volume)
    b.add_grip("gripper", PointSet(sc.positions[sc.gripped]), FunctionPath(sc.gripper_position))
    b.hold_nodes(sc.held_node_mask())
    order = np.concatenate([np.flatnonzero(skin), np.flatnonzero(inner)])
    return b.build(), order


def test_engine_reproduces_the_orange_peel() -> None:
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=2, frames=FRAMES, record_every=3)
    scene, order = orange_on_the_engine(sim)
    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(16, space.dim)))[[4, 2]]
    col = dict(zip(space.names, params.T, strict=True))
    model = scene.model(2)
    model.set_material("skin", E=col["E"], rho=col["rho"] * DENSITY_UNIT, fracture_stretch=col["sigma_s"],
                       eta=col["eta_s"], residual=col["r_s"], fibre_ratio=col["f_s"])
    model.set_material("interior", E=col["E"], rho=col["rho"] * DENSITY_UNIT, fracture_stretch=col["sigma_i"],
                       eta=col["eta_i"], residual=col["r_i"])
    records = Engine(scene, backend="taichi", arch="cpu").run(model, FRAMES, 3)
    for rec, res in zip(records, sim.simulate(params), strict=True):
        assert rec.ok and res.ok
        assert rec.substeps + rec.settle_substeps == res.stats.substeps
        xe, xo = np.stack(rec.positions), res.trajectory.positions[:, order]
        motion = np.abs(xo[-1] - xo[0]).max()
        assert motion > 1e-3
        assert np.abs(xe - xo).max() < 1e-4 * motion
        np.testing.assert_allclose(np.stack(rec.damage), res.trajectory.damage[:, order], atol=1e-5)
