"""The Taichi backend's node boxes: the grid's clear and update read only the nodes of each run's scatter box.

Each run keeps the box of grid nodes its last scatter touched (``BOX_LAST``, which the next clear zeroes) and
the one the scatter under way grows (``BOX_NEXT``, which the grid update reads); g2p moves the second into the
first. Outside them a run's grid holds zeros, so restricting the two grid loops to them changes no number: on
the CPU (serialised scatter) the state matches loops over the whole grid bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from engine_benchmarks import load

pytest.importorskip("taichi")

from invphys_anisompm.backends.taichi_backend import BOX_LAST, BOX_NEXT, TaichiBackend
from invphys_anisompm.testing import build_scene

#: the host's computation of a scatter's node box, which the GPU check uses too
#: (examples/anisompm/benchmarks/check_grid_box.py)
scatter_box = load("check_grid_box").scatter_box

SCENE = build_scene(settle_seconds=0.06)
MODEL = SCENE.model(2).set_material("paste", E=[3e4, 6e4], eta=[0.02, 0.05]).set_friction("wire", [0.3, 0.0])
STATE = ("x", "v", "C", "F", "d", "dtil", "gv", "gm", "gd", "gg", "imp", "work")
N_STEPS = 40
NSUB = [N_STEPS, 25]   # the second run idles for the last 15 substeps


def _loaded(scene=SCENE) -> TaichiBackend:
    """A CPU backend of MODEL's two runs, moving (random kinematics, an initial velocity) so that the scatter's
    nodes change from substep to substep."""
    backend = TaichiBackend(scene, 2, arch="cpu")
    backend.load(MODEL.table(), MODEL.friction)
    v = np.zeros((2, SCENE.n_particles, 3), np.float32)
    v[..., 0] = 0.5
    backend.v.from_numpy(v)
    kin = np.random.default_rng(0).normal(scale=1e-3, size=(2, N_STEPS, backend.nk1, 6))
    backend.set_frame(np.full(2, 2e-4), np.array(NSUB), kin, damage_on=True)
    return backend


def _nonzero_nodes(backend: TaichiBackend, b: int) -> np.ndarray:
    """(n, 3) indices of run b's grid nodes holding anything."""
    held = (backend.gv.to_numpy()[b] != 0).any(-1) | (backend.gm.to_numpy()[b] != 0) \
        | (backend.gd.to_numpy()[b] != 0).any(-1) | (backend.gg.to_numpy()[b] != 0)
    return np.argwhere(held)


def test_the_last_box_is_the_scatters_and_holds_every_node_of_the_grid() -> None:
    backend = _loaded()
    G = backend.options.grid
    empty = [G] * 3 + [-1] * 3
    for k in range(N_STEPS):
        expected = [scatter_box(x, backend.options.dx, G) for x in backend.x.to_numpy()]
        before = backend.box.to_numpy()
        for launch in backend._stages(k).values():
            launch()
        box = backend.box.to_numpy()
        for b in range(2):
            if k < NSUB[b]:
                assert np.array_equal(box[b, BOX_LAST], expected[b]), (k, b)   # exactly the scatter's nodes
                assert np.array_equal(box[b, BOX_NEXT], empty)                   # emptied for the next scatter
            else:
                assert np.array_equal(box[b], before[b])                         # an idle run's stay
            nodes = _nonzero_nodes(backend, b)
            lo, hi = box[b, BOX_LAST, :3], box[b, BOX_LAST, 3:]
            assert len(nodes) and np.all(nodes >= lo) and np.all(nodes <= hi), (k, b)
            assert np.prod(hi - lo + 1) < 0.5 * G ** 3                             # far from the whole grid


def test_boxed_grid_loops_equal_whole_grid_loops_bit_for_bit() -> None:
    boxed, whole = _loaded(), _loaded()
    G = whole.options.grid
    full = np.broadcast_to(np.array([0, 0, 0, G - 1, G - 1, G - 1], np.int32), (2, 6))
    for k in range(N_STEPS):
        boxed_stages, whole_stages = boxed._stages(k), whole._stages(k)
        for stage in boxed_stages:
            boxed_stages[stage]()
            if stage == "grid":   # restore the loops over the whole grid for the other backend
                continue
            whole_stages[stage]()
            if stage == "p2g":
                box = whole.box.to_numpy()
                box[:, BOX_NEXT] = full   # the update reads every node, and g2p hands the clear every node
                whole.box.from_numpy(box)
                whole_stages["grid"]()
        for name in STATE:
            assert np.array_equal(getattr(boxed, name).to_numpy(), getattr(whole, name).to_numpy()), (k, name)


def test_a_new_run_in_a_slot_gets_empty_boxes_and_the_others_keep_theirs() -> None:
    backend = _loaded()
    G = backend.options.grid
    backend.advance(5)
    before = backend.box.to_numpy()
    backend.load_slots(np.array([1]), MODEL.table()[1:], MODEL.friction[1:])
    after = backend.box.to_numpy()
    assert np.array_equal(after[0], before[0])
    assert np.all(after[1] == [[G] * 3 + [-1] * 3] * 2)
    assert len(_nonzero_nodes(backend, 1)) == 0


def test_the_update_by_columns_equals_the_serialised_update_over_nodes() -> None:
    """The GPU's form of the grid update (one thread per x-z column of the box, walking y; here on the CPU
    with ``deterministic=False``) gives the serialised loop's node velocities bit for bit from the same grid,
    and its impulse and work sums to float rounding (their order differs)."""
    serial = _loaded()
    parallel = _loaded(build_scene(settle_seconds=0.06, deterministic=False))
    G = serial.options.grid
    for k in range(3):
        stages = serial._stages(k)
        stages["clear"]()
        stages["p2g"]()
        for name in ("x", "v", "C", "F", "d", "dtil", "gv", "gm", "gd", "gg", "box", "nsub", "dt", "kin", "damp",
                     "don", "imp", "work"):
            getattr(parallel, name).from_numpy(getattr(serial, name).to_numpy())
        stages["grid"]()
        parallel._stages(k)["grid"]()
        assert np.array_equal(serial.gv.to_numpy(), parallel.gv.to_numpy()), k
        assert np.allclose(serial.imp.to_numpy(), parallel.imp.to_numpy(), rtol=1e-5, atol=1e-12)
        assert np.abs(serial.imp.to_numpy()).max() > 0   # the wire and the grip pushed: the sums are checked
        if k == 0:   # its own (parallel) atomic scatter hands the update the whole grid instead
            parallel._stages(k)["p2g"]()
            assert np.all(parallel.box.to_numpy()[:, BOX_NEXT] == [0, 0, 0, G - 1, G - 1, G - 1])
        stages["g2p"]()
