"""The Taichi backend's fused substep (``fused=True``; the orange peel's ``taichi_fused``) on the CPU.

A fused substep is one G2P2G kernel (each particle's g2p of substep ``k - 1`` from one grid buffer, then its
scatter of substep ``k`` into the other) and one grid kernel (the update of ``k``'s grid and the clear of
the other buffer), instead of clear, p2g, grid update and g2p. On the CPU (serialised scatter and update) it
does the same sums in the same order; compiled into other kernels (fast math) its arithmetic rounds
differently, so it must give the plain path's state to float rounding (worst ~3e-5 of an array's scale
after four frames; a substep's kinematics or grid buffer mixed up is far more): over frames whose substep
counts differ per run and change parity (the buffers' and box slots' cycles), with damage evolving, both
g2p forms, CUDA's matrix layout, re-sorted particles, the g2p state in registers or written back, and slots refilled by
continuous batching. The tiled (CUDA) form is checked on a GPU by
``examples/anisompm/benchmarks/bench_fused.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm.backends.taichi_backend import FUSED_SLOTS, GRAPH_SUBSTEPS, TaichiBackend
from invphys_anisompm.testing import build_scene
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.simulator import OrangePeelSimulator

from invphys.core.dataset import RunIdentity

SCENE = build_scene(settle_seconds=0.06)
MODEL = SCENE.model(2).set_material("paste", E=[3e4, 6e4], eta=[0.02, 0.05]).set_friction("wire", [0.3, 0.0])
PARTICLES = ("x", "v", "C", "F", "d", "dtil")
#: per frame, each run's substeps: graphs and single substeps, a run idle from inside a graph on, a run with no
#: substep at all, odd and even counts (the next frame's first buffer and slot follow from them)
FRAMES = [(2 * GRAPH_SUBSTEPS + 3, GRAPH_SUBSTEPS + 2), (5, 0), (GRAPH_SUBSTEPS, 7), (1, 4)]
#: the largest difference from the plain path allowed, as a fraction of each array's largest value
ROUNDING = 1e-4


def _assert_close(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert got.keys() == want.keys()
    for key, value in want.items():
        scale = max(float(np.abs(value).max()), 1e-12)
        assert np.abs(got[key] - value).max() <= ROUNDING * scale, (key, np.abs(got[key] - value).max() / scale)


def _frames(fused: bool, scene=SCENE, **options) -> tuple[TaichiBackend, dict[str, np.ndarray]]:
    """MODEL's two runs from a moving, strained, damaged state (so stress, damage Laplacian and APIC terms
    act) through FRAMES with per-substep kinematics; the backend and its particle state, force sums and
    grid mass after each frame (keys ``name@frame``)."""
    backend = TaichiBackend(scene, 2, arch="cpu", fused=fused, **options)
    backend.load(MODEL.table(), MODEL.friction)
    B, N = 2, scene.n_particles
    rng = np.random.default_rng(0)
    backend.set_particle_array("d", np.where(rng.uniform(size=(B, N)) < 0.3, rng.uniform(0.0, 0.6, (B, N)), 0.0))
    backend.set_particle_array("F", np.eye(3) + 0.05 * rng.standard_normal((B, N, 3, 3)))
    backend.set_particle_array("v", 0.1 * rng.standard_normal((B, N, 3)))
    out: dict[str, np.ndarray] = {"d@start": backend.particle_array("d")}
    for f, nsub in enumerate(FRAMES):
        n = max(nsub)
        kin = rng.normal(scale=1e-3, size=(B, n, backend.nk1, 6))
        backend.set_frame(np.full(B, 2e-4), np.array(nsub), kin, damage_on=True)
        backend.advance(n)
        backend.sync()
        out.update({f"{k}@{f}": backend.particle_array(k) for k in PARTICLES})
        imp, work = backend.kinematic_sums()
        out.update({f"imp@{f}": imp, f"work@{f}": work, f"grid_mass@{f}": backend.grid_mass()})
    return backend, out


@pytest.mark.parametrize("options", [{}, {"g2p": "loop", "component_major": True},
                                     {"particle_order": "hilbert", "resort_every": 8}, {"fused_registers": False}],
                         ids=["unrolled", "loop-cuda-layout", "resorted", "written-back"])
def test_fused_substeps_agree_with_the_plain_path(options):
    _, want = _frames(False, **{k: v for k, v in options.items() if k != "fused_registers"})
    fused, got = _frames(True, **options)
    # the fused path really ran: its own stages, two grid buffers, its box slots
    assert list(fused._stages(0)) == ["fclear", "fused", "fgrid"]
    assert fused.gm.shape[0] == 2 * fused.batch and fused.box.shape[1] == FUSED_SLOTS
    if "resort_every" in options:
        assert fused.resorter.sorts > 0
    assert np.abs(want[f"d@{len(FRAMES) - 1}"] - want["d@start"]).max() > 1e-3   # damage evolved
    assert np.abs(want["x@0"] - SCENE.positions[None]).max() > 0   # the substeps did something
    assert fused.fused_registers == options.get("fused_registers", True)
    _assert_close(got, want)


def test_after_advance_only_the_last_grid_is_left():
    """The fused path leaves each run's last scatter in one buffer, inside one box slot (what the next
    advance's clear zeroes), and zeros elsewhere; grid_mass is that grid's mass, as on the plain path."""
    backend, out = _frames(True)
    G = backend.options.grid
    gm = backend.gm.to_numpy().reshape(2, backend.batch, G, G, G)
    box = backend.box.to_numpy()
    for b, nsub in enumerate(FRAMES[-1]):
        last = gm[(nsub - 1) % 2, b]
        assert not gm[nsub % 2, b].any()
        lo, hi = box[b, (nsub - 1) % FUSED_SLOTS, :3], box[b, (nsub - 1) % FUSED_SLOTS, 3:]
        inside = last[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1]
        assert inside.sum() == last.sum() > 0
        others = [s for s in range(FUSED_SLOTS) if s != (nsub - 1) % FUSED_SLOTS]
        assert all(box[b, s, 3] == -1 for s in others)          # the other slots are empty
    np.testing.assert_allclose(out[f"grid_mass@{len(FRAMES) - 1}"], gm.sum(axis=(0, 2, 3, 4)))


def _orange(**kw) -> OrangePeelSimulator:
    return OrangePeelSimulator(backend="taichi", preset="tiny", arch="cpu", batch_size=2, frames=4,
                               settle_seconds=0.02, **kw)


def test_orange_runs_fused_equal_plain_in_continuous_batching():
    """Three runs through two slots (a slot is refilled: both grid buffers wiped): the same substeps, positions
    and per-frame series to float rounding; the option reaches the backend and is no part of a run's identity."""
    params = parameter_space().denormalize(np.random.default_rng(3).uniform(size=(3, parameter_space().dim)))
    plain, fused = _orange(scheduling="continuous"), _orange(scheduling="continuous", taichi_fused=True)
    a, b = plain.simulate(params), fused.simulate(params)
    assert fused.engine.backend(2).fused and not plain.engine.backend(2).fused
    assert RunIdentity.of(fused) == RunIdentity.of(plain)
    for ra, rb in zip(a, b, strict=True):
        assert ra.ok and rb.ok
        assert ra.stats.substeps == rb.stats.substeps
        want = {"x": np.stack(ra.trajectory.positions),
                **{key: np.asarray(ra.trajectory.extra[key]) for key in ("frame_mean_damage", "frame_work")}}
        got = {"x": np.stack(rb.trajectory.positions),
               **{key: np.asarray(rb.trajectory.extra[key]) for key in ("frame_mean_damage", "frame_work")}}
        _assert_close(got, want)


def test_kernel_times_name_the_fused_stages():
    backend, _ = _frames(True)
    backend.set_frame(np.full(2, 1e-4), np.array([8, 8]), np.zeros((2, 8, backend.nk1, 6)), damage_on=True)
    times = backend.kernel_times(3)
    assert set(times) == {"fused", "fgrid"} and all(t > 0 for t in times.values())


def test_parallel_cpu_scatter_fused_agrees_with_plain():
    """Without the serialised scatter (``deterministic=False``: the GPU's loops, parallel float atomics and
    the grid kernel's merged update-and-clear pass over columns) the fused path agrees with the plain one
    (to float rounding of the sums' order)."""
    scene = build_scene(settle_seconds=0.06, deterministic=False)
    _, want = _frames(False, scene)
    _, got = _frames(True, scene)
    _assert_close(got, want)


def test_fused_advance_short_of_the_frame_is_refused():
    """A fused advance ends with every run's last g2p; fewer substeps than a run's frame would leave it mid-way."""
    from invphys.core.errors import InvphysError

    backend = TaichiBackend(SCENE, 2, arch="cpu", fused=True)
    backend.load(MODEL.table(), MODEL.friction)
    backend.set_frame(np.full(2, 1e-4), np.array([4, 2]), np.zeros((2, 4, backend.nk1, 6)), damage_on=True)
    with pytest.raises(InvphysError, match="short of the frame's 4 substeps"):
        backend.advance(3)
    backend.advance(4)
