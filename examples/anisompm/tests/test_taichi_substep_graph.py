"""The Taichi backend's substeps as graphs: the same kernels in the same order as launching them one by one.

``TaichiBackend.advance`` records a frame's substeps in Taichi graphs (``GRAPH_SUBSTEPS`` per launch, single
ones for the rest), which saves the host ~0.7-1 ms of Python per substep on a GPU. On the CPU (serialised
scatter) it must give the state of the one-by-one launches bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm.backends.taichi_backend import GRAPH_SUBSTEPS, TaichiBackend
from invphys_anisompm.testing import build_scene

SCENE = build_scene(settle_seconds=0.06)
MODEL = SCENE.model(2).set_material("paste", E=[3e4, 6e4], eta=[0.02, 0.05]).set_friction("wire", [0.3, 0.0])
STATE = ("x", "v", "C", "F", "d", "dtil", "gv", "gm", "gd", "gg", "imp", "work")


def _loaded(n_steps: int, nsub: list[int]) -> TaichiBackend:
    """A CPU backend of MODEL's two runs, a frame of ``n_steps`` substeps with per-substep kinematics (so
    each substep's ``k`` matters) and its own substep count per run (so ``k < nsub`` gates differ)."""
    backend = TaichiBackend(SCENE, 2, arch="cpu")
    backend.load(MODEL.table(), MODEL.friction)
    kin = np.random.default_rng(0).normal(scale=1e-3, size=(2, n_steps, backend.nk1, 6))
    backend.set_frame(np.full(2, 2e-5), np.array(nsub), kin, damage_on=True)
    return backend


def test_graph_substeps_equal_one_by_one_launches_bit_for_bit():
    n = 2 * GRAPH_SUBSTEPS + 3          # two whole graphs and three single substeps
    nsub = [n, GRAPH_SUBSTEPS + 2]      # the second run idles from inside the second graph on
    graphed, direct = _loaded(n, nsub), _loaded(n, nsub)
    graphed.advance(n)
    for k in range(n):
        for launch in direct._stages(k).values():
            launch()
    graphed.sync()
    moved = np.abs(graphed.x.to_numpy() - graphed.x0.to_numpy()[None]).max()
    assert moved > 0                    # the substeps did something
    for name in STATE:
        a, b = getattr(graphed, name).to_numpy(), getattr(direct, name).to_numpy()
        assert np.array_equal(a, b, equal_nan=True), name


def test_a_run_past_its_substeps_is_left_as_it_was():
    n = GRAPH_SUBSTEPS + 1
    short, long_ = _loaded(n, [n, 0]), _loaded(n, [n, 0])
    x0 = short.x.to_numpy()[1].copy()
    short.advance(n)
    long_.advance(1)
    assert np.array_equal(short.x.to_numpy()[1], x0)     # run 1 had no substeps in this frame
    assert not np.array_equal(short.x.to_numpy()[0], long_.x.to_numpy()[0])
