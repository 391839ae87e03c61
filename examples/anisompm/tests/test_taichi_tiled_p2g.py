"""The tiled P2G's CPU-checkable parts: particle orders, reads in the scene's order, clear errors.

The tiled scatter itself needs CUDA shared memory; on a GPU ``examples/anisompm/benchmarks/bench_tiled_p2g.py``
checks that its grid equals the atomic scatter's to float rounding and that whole runs agree as closely as two
atomic runs do (``examples/anisompm/benchmarks/results/tiled_p2g_fixed_point_sums_paper_h100.json``).
The engine's test scene (``invphys_anisompm.testing``) serves as the scene; the orange peel where a paper-sized
scene is needed (the tiles' compactness over ~200 tiles) and where its config's ``taichi_*`` knobs are tested.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm import Engine
from invphys_anisompm.backends.particle_order import hilbert_index, hilbert_order, morton_order
from invphys_anisompm.backends.taichi_backend import TaichiBackend
from invphys_anisompm.testing import build_scene
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.simulator import OrangePeelSimulator

from invphys.core.dataset import RunIdentity
from invphys.core.errors import InvphysError

SCENE = build_scene(settle_seconds=0.04)
MODEL = SCENE.model(2).set_material("paste", E=[3e4, 6e4], eta=[0.02, 0.05]).set_friction("wire", [0.3, 0.0])


def _tiny(**kw) -> OrangePeelSimulator:
    return OrangePeelSimulator(backend="taichi", preset="tiny", arch="cpu", batch_size=2, frames=3, **kw)


def _box_nodes(base: np.ndarray, tile: int) -> np.ndarray:
    n = len(base) // tile * tile
    b = base[:n].reshape(-1, tile, 3)
    return (b.max(axis=1) - b.min(axis=1) + 3).prod(axis=1)


def test_curve_orders_are_permutations_with_compact_tiles_hilbert_the_most():
    scene = OrangePeelSimulator(backend="taichi", preset="paper", arch="cpu").engine_scene.engine  # no kernels
    o = scene.options
    base = np.clip((scene.positions / o.dx - 0.5).astype(int), 0, o.grid - 3)
    boxes = {}
    for name, order in (("morton", morton_order), ("hilbert", hilbert_order)):
        perm = order(scene.positions, o.dx, o.grid)
        assert np.array_equal(np.sort(perm), np.arange(scene.n_particles))
        boxes[name] = _box_nodes(base[perm], 256)
    # tiles of consecutive particles span far fewer grid nodes along a curve than in the scene's order, and
    # the Hilbert curve (no jumps) leaves fewer tiles too large for the shared-memory box (1,024 nodes)
    assert np.median(boxes["morton"]) < 0.5 * np.median(_box_nodes(base, 256))
    assert np.median(boxes["hilbert"]) < 0.8 * np.median(boxes["morton"])
    assert (boxes["hilbert"] > 1024).sum() < 0.5 * (boxes["morton"] > 1024).sum()


@pytest.mark.parametrize("bits", [1, 2, 3, 5])
def test_hilbert_index_visits_every_cell_once_stepping_to_a_neighbour(bits):
    n = 1 << bits
    cells = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    index = hilbert_index(cells, bits)
    assert np.array_equal(np.sort(index), np.arange(n ** 3))
    path = cells[np.argsort(index)]
    assert np.all(np.abs(np.diff(path, axis=0)).sum(axis=1) == 1)   # each step: one cell along one axis


def test_tiled_scatter_needs_cuda_and_auto_picks_atomic_on_cpu():
    scene = SCENE
    with pytest.raises(InvphysError, match="needs CUDA"):
        TaichiBackend(scene, 2, arch="cpu", p2g="tiled")
    with pytest.raises(InvphysError, match="p2g must be"):
        TaichiBackend(scene, 2, arch="cpu", p2g="shared")
    with pytest.raises(InvphysError, match="particle_order must be"):
        TaichiBackend(scene, 2, arch="cpu", particle_order="peano")
    assert TaichiBackend(scene, 2, arch="cpu", p2g="auto").p2g == "atomic"
    sim = _tiny(taichi_p2g="tiled")
    with pytest.raises(InvphysError, match="needs CUDA"):
        sim.simulate(parameter_space().denormalize(np.full((1, parameter_space().dim), 0.5)))


def test_scatter_and_g2p_choices_are_not_part_of_the_run_identity():
    assert RunIdentity.of(_tiny(taichi_p2g="tiled")) == RunIdentity.of(_tiny(taichi_p2g="atomic")) \
        == RunIdentity.of(_tiny())
    looped = _tiny(taichi_g2p="loop")
    assert RunIdentity.of(looped) == RunIdentity.of(_tiny())
    assert looped.engine.backend(2).g2p == "loop"   # the food's knob reaches the backend


@pytest.mark.parametrize("order", ["hilbert", "morton"])
def test_curve_particle_order_returns_the_scene_order(order):
    """The same runs with the device's particles along a curve (Hilbert: the tiled scatter's order) and in
    the scene's: every record comes back in the scene's order and agrees up to the scatter's summation order."""
    a = Engine(SCENE, backend="taichi", arch="cpu").run(MODEL, 3, 1)
    b = Engine(SCENE, backend="taichi", arch="cpu", particle_order=order).run(MODEL, 3, 1)
    for ra, rb in zip(a, b, strict=True):
        assert ra.ok and rb.ok
        pa, pb = np.stack(ra.positions), np.stack(rb.positions)
        assert pa.shape == pb.shape
        scale = np.abs(pa - pa[0]).max()  # how far the particles moved
        assert scale > 1e-4
        assert np.abs(pb - pa).max() < 1e-3 * scale
        np.testing.assert_allclose(np.stack(rb.damage), np.stack(ra.damage), atol=1e-4)



def _advance(backend, n: int) -> None:
    """``n`` substeps of dt 2e-4 with damage on and the grips still."""
    B = backend.batch
    nk = max(len(backend.scene.kinematic_names), 1)
    backend.set_frame(np.full(B, 2e-4), np.full(B, n), np.zeros((B, n, nk, 6)), damage_on=True)
    backend.advance(n)


def _substeps(engine: Engine, n: int = 3) -> dict[str, np.ndarray]:
    """``n`` substeps from MODEL's loaded runs with random damage, deformation and velocities already present
    (so the stress, g2p's damage Laplacian and the APIC terms all act); the particle state after them."""
    B, N = MODEL.n_envs, SCENE.n_particles
    backend = engine.backend(B)
    backend.load(MODEL.table(), MODEL.friction)
    rng = np.random.default_rng(0)
    backend.set_particle_array("d", rng.uniform(0.0, 0.6, (B, N)))
    backend.set_particle_array("F", np.eye(3) + 0.05 * rng.standard_normal((B, N, 3, 3)))
    backend.set_particle_array("v", 0.1 * rng.standard_normal((B, N, 3)))
    _advance(backend, n)
    backend.sync()
    return {k: backend.particle_array(k) for k in ("x", "v", "C", "F", "d")}


def test_looped_g2p_does_the_same_sums_on_cpu_and_auto_keeps_the_cpu_unrolled():
    """g2p with loops over two axes (CUDA's default: half the registers) does the same sums in the same
    order as the 27 unrolled nodes: the runs agree to float rounding (the compiler contracts products
    differently); ``auto`` keeps the CPU on the unrolled form, so CPU results stay bit for bit."""
    auto = Engine(SCENE, backend="taichi", arch="cpu")
    assert auto.backend(2).g2p == "unrolled"
    plain = _substeps(auto)
    looped_engine = Engine(SCENE, backend="taichi", arch="cpu", g2p="loop")
    assert looped_engine.backend(2).g2p == "loop"
    looped = _substeps(looped_engine)
    # measured: <= 8e-7 of each array's largest value on an Intel Xeon, 2.5e-6 (v) on an AMD EPYC (the
    # compiler contracts products per CPU); a wrong weight or node is off by 1e-2 or more
    for k, ref in plain.items():
        scale = float(np.abs(ref).max())
        assert np.abs(looped[k] - ref).max() <= 1e-5 * scale, (k, np.abs(looped[k] - ref).max() / scale)
    # the damage moved in these substeps (g2p's Laplacian term acts), and both forms moved it alike
    start = np.random.default_rng(0).uniform(0.0, 0.6, plain["d"].shape).astype(np.float32)
    assert np.abs(plain["d"] - start).max() > 0.05
    with pytest.raises(InvphysError, match="g2p must be"):
        TaichiBackend(SCENE, 2, arch="cpu", g2p="rolled")


def test_reads_are_new_arrays_in_the_scene_order():
    """``read``/``read_slots`` return new host arrays in the scene's particle order (the device gathers
    them), so records may keep views: a later substep does not change what an earlier read returned."""
    scene = SCENE
    for order in ("scene", "hilbert"):
        backend = TaichiBackend(scene, 2, arch="cpu", particle_order=order)
        assert backend.reads_are_new
        backend.load(MODEL.table(), MODEL.friction)
        x0, _ = backend.read()
        np.testing.assert_array_equal(x0[1], scene.positions.astype(np.float32))   # scene order
        kept = x0.copy()
        _advance(backend, 2)
        x1, _ = backend.read()
        xs, ds = backend.read_slots(np.array([1]))
        assert not np.shares_memory(x0, x1) and not np.array_equal(x1, kept)
        np.testing.assert_array_equal(x0, kept)   # the earlier read is untouched
        np.testing.assert_array_equal(xs[0], x1[1])
        assert ds.shape == (1, scene.n_particles)


def _kernel(fn, *names):
    """A Taichi kernel of ``fn`` with ndarray arguments ``names`` (this module's annotations are strings)."""
    import taichi as ti

    fn.__annotations__ = {n: ti.types.ndarray() for n in names}
    return ti.kernel(fn)


def test_fixed_point_scale_cannot_overflow_and_rounds_to_2e_minus_22_of_the_bound():
    """The tiled scatter's integer sums (CUDA) rest on three CPU-checkable functions: a tile's bound as the
    bits of a non-negative float (ordered as the floats are, a NaN above infinity), the power-of-two scale
    from it, and the rounding of a scaled share. For bounds over 60 decades and zero: a share at the bound
    scales to at most 2**22 (where the rounding is exact), a whole tile's shares at the bound stay below
    2**31, the scale is an exact power of two with an exact inverse, and one share is rounded to at most
    2**-22 of the bound, to the nearest integer."""
    import taichi as ti
    from invphys_anisompm.backends.taichi_backend import (
        F32_INF_BITS,
        TILE,
        _fixed_point_scale,
        _momentum_bound_bits,
        _round_to_int,
        ensure_taichi,
    )

    ensure_taichi("cpu")
    bounds = np.concatenate([[0.0, 1e-38], np.logspace(-30, 30, 121)]).astype(np.float32)
    out = ti.ndarray(ti.f32, (len(bounds), 2))
    src = ti.ndarray(ti.f32, (len(bounds),))
    src.from_numpy(bounds)

    def scales(b, o):
        for i in range(b.shape[0]):
            s, inv = _fixed_point_scale(ti.bit_cast(b[i], ti.i32))
            o[i, 0] = s
            o[i, 1] = inv

    _kernel(scales, "b", "o")(src, out)
    s, inv = out.to_numpy().astype(np.float64).T
    assert np.all(s * inv == 1.0)
    assert np.all(np.log2(s) == np.round(np.log2(s)))                    # powers of two: exact scaling
    assert np.all(bounds.astype(np.float64) * s <= 2.0 ** 22)              # one share: exact rounding
    assert np.all(TILE * 0.42 * bounds.astype(np.float64) * s < 2.0 ** 31)  # a node's sum: no overflow
    big = bounds > 1e-30
    assert np.all(0.5 * inv[big] <= 2.0 ** -22 * bounds[big])           # rounding step vs the bound

    # ties to even, both signs, up to the 2**22 the scale allows
    x = np.concatenate([np.arange(-6, 6.5, 0.25), [2.0 ** 22, -2.0 ** 22, 2.0 ** 22 - 0.5, 4194301.5, 1e6 + 0.5,
                                                   -1e6 - 0.5, 123456.7, -0.49999997]]).astype(np.float32)
    xs = ti.ndarray(ti.f32, (len(x),))
    xs.from_numpy(x)
    rounded = ti.ndarray(ti.i32, (len(x),))

    def round_all(v, o):
        for i in range(v.shape[0]):
            o[i] = _round_to_int(v[i])

    _kernel(round_all, "v", "o")(xs, rounded)
    np.testing.assert_array_equal(rounded.to_numpy(), np.rint(x.astype(np.float64)).astype(np.int64))

    bits = ti.ndarray(ti.i32, (4,))
    mv = ti.ndarray(ti.math.vec3, (4,))
    aff = ti.ndarray(ti.math.mat3, (4,))
    mv.from_numpy(np.array([[0, 0, 0], [1, -2, 0.5], [0, np.nan, 0], [np.inf, 0, 0]], np.float32))
    aff.from_numpy(np.stack([np.zeros((3, 3)), np.diag([1.0, -1.0, 2.0]), np.zeros((3, 3)),
                             np.zeros((3, 3))]).astype(np.float32))

    def bound_bits(m, a, o):
        for i in range(m.shape[0]):
            o[i] = _momentum_bound_bits(m[i], a[i], 0.1)

    _kernel(bound_bits, "m", "a", "o")(mv, aff, bits)
    got = bits.to_numpy()
    assert got[0] == 0
    assert got[1] == np.float32(2.0 + 0.15).view(np.int32)     # row 1: |-2| + 1.5 * 0.1 * |-1|
    assert got[2] >= F32_INF_BITS and got[3] >= F32_INF_BITS      # non-finite: the tile scatters globally


def test_weight_and_damage_sums_in_fixed_point_cannot_overflow_and_match_the_float_sums():
    """The tiled scatter (CUDA) sums each node's B-spline weights ``w`` and damage shares ``w d`` (``d`` in
    [0, 1]; a tile with another ``d`` scatters globally) as integers of 2**-23 (``WEIGHT_SCALE``): the largest
    share (0.75**3) scales below 2**22, where ``_round_to_int`` is exact, and a node's TILE shares below
    2**31. A tile's shares rounded and summed as the kernel does (on the CPU) equal the float64 sums to half
    a unit per share, and every node a particle reaches keeps a nonzero weight sum."""
    import taichi as ti
    from invphys_anisompm.backends.taichi_backend import TILE, WEIGHT_SCALE, _round_to_int, ensure_taichi

    assert 0.75 ** 3 * WEIGHT_SCALE <= 2.0 ** 22
    assert TILE * 0.75 ** 3 * WEIGHT_SCALE < 2.0 ** 31
    ensure_taichi("cpu")
    rng = np.random.default_rng(0)
    fx = rng.uniform(0.5, 1.5, size=(TILE, 3))   # a tile's particles, each in its base cell (worst case: one cell)
    per_axis = np.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], axis=1)
    w = np.einsum("pi,pj,pk->pijk", per_axis[:, :, 0], per_axis[:, :, 1], per_axis[:, :, 2]).reshape(TILE, 27)
    d = np.where(rng.random(TILE) < 0.5, 1.0, rng.uniform(0.0, 1.0, TILE))[:, None]  # half fully damaged

    def to_units(v, o):
        for p, n in ti.ndrange(v.shape[0], v.shape[1]):
            o[p, n] = _round_to_int(v[p, n] * WEIGHT_SCALE)

    kernel = _kernel(to_units, "v", "o")
    sums = {}
    for name, shares in (("w", w.astype(np.float32)), ("w d", w.astype(np.float32) * d.astype(np.float32))):
        src = ti.ndarray(ti.f32, w.shape)
        src.from_numpy(shares)
        units = ti.ndarray(ti.i32, w.shape)
        kernel(src, units)
        sums[name] = units.to_numpy().astype(np.int64).sum(axis=0)
        assert sums[name].max() < 2 ** 31
        exact = shares.astype(np.float64).sum(axis=0)
        assert np.all(np.abs(sums[name] / WEIGHT_SCALE - exact) <= TILE * 0.5 / WEIGHT_SCALE), name
    assert np.all(sums["w"] > 0)   # touched nodes stay touched (the flush skips a zero sum)
