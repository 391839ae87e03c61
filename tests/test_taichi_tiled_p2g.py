"""The tiled P2G's CPU-checkable parts: Morton particle order, reads in the scene's order, clear errors.

The tiled scatter itself needs CUDA shared memory; on a GPU ``benchmarks/bench_tiled_p2g.py`` checks
that its grid equals the atomic scatter's to float rounding and that whole runs agree as closely as two
atomic runs do (``benchmarks/results/tiled_p2g_paper_h200.json``).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm import Engine
from invphys_anisompm.backends.taichi_backend import TaichiBackend, morton_order
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.simulator import OrangePeelSimulator

from invphys.core.dataset import RunIdentity
from invphys.core.errors import InvphysError


def _tiny(**kw) -> OrangePeelSimulator:
    return OrangePeelSimulator(backend="taichi", preset="tiny", arch="cpu", batch_size=2, frames=3, **kw)


def _box_nodes(base: np.ndarray, tile: int) -> np.ndarray:
    n = len(base) // tile * tile
    b = base[:n].reshape(-1, tile, 3)
    return (b.max(axis=1) - b.min(axis=1) + 3).prod(axis=1)


def test_morton_order_is_a_permutation_with_compact_tiles():
    scene = OrangePeelSimulator(backend="taichi", preset="paper", arch="cpu").engine_scene.engine  # no kernels
    o = scene.options
    perm = morton_order(scene.positions, o.dx, o.grid)
    assert np.array_equal(np.sort(perm), np.arange(scene.n_particles))
    base = np.clip((scene.positions / o.dx - 0.5).astype(int), 0, o.grid - 3)
    # tiles of consecutive particles span far fewer grid nodes in Morton order than in the scene's order
    assert np.median(_box_nodes(base[perm], 256)) < 0.5 * np.median(_box_nodes(base, 256))


def test_tiled_scatter_needs_cuda_and_auto_picks_atomic_on_cpu():
    scene = _tiny().engine_scene.engine
    with pytest.raises(InvphysError, match="needs CUDA"):
        TaichiBackend(scene, 2, arch="cpu", p2g="tiled")
    with pytest.raises(InvphysError, match="p2g must be"):
        TaichiBackend(scene, 2, arch="cpu", p2g="shared")
    with pytest.raises(InvphysError, match="particle_order must be"):
        TaichiBackend(scene, 2, arch="cpu", particle_order="hilbert")
    assert TaichiBackend(scene, 2, arch="cpu", p2g="auto").p2g == "atomic"
    sim = _tiny(taichi_p2g="tiled")
    with pytest.raises(InvphysError, match="needs CUDA"):
        sim.simulate(parameter_space().denormalize(np.full((1, parameter_space().dim), 0.5)))


def test_scatter_choice_is_not_part_of_the_run_identity():
    assert RunIdentity.of(_tiny(taichi_p2g="tiled")) == RunIdentity.of(_tiny(taichi_p2g="atomic")) \
        == RunIdentity.of(_tiny())


def test_morton_particle_order_returns_the_scene_order():
    """The same runs with the device's particles in Morton order (the tiled scatter's order) and in the
    scene's: every record comes back in the scene's order and agrees up to the scatter's summation order."""
    space = parameter_space()
    params = space.denormalize(np.random.default_rng(3).uniform(size=(2, space.dim)))
    plain = _tiny()
    morton = _tiny()
    morton._engine = Engine(morton.engine_scene.engine, backend="taichi", arch="cpu", particle_order="morton")
    a, b = plain.simulate(params), morton.simulate(params)
    for ra, rb in zip(a, b, strict=True):
        assert ra.ok and rb.ok
        pa, pb = ra.trajectory.positions, rb.trajectory.positions
        assert pa.shape == pb.shape
        scale = np.abs(pa - pa[0]).max()  # how far the particles moved
        assert np.abs(pb - pa).max() < 1e-3 * scale
        np.testing.assert_allclose(rb.trajectory.damage, ra.trajectory.damage, atol=1e-4)
