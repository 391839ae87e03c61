"""The particle matrices' two layouts (``MATRIX_STATE`` in ``taichi_backend.py``), checked on the CPU.

CUDA stores C and F component-major, ``(B, 9, N)``; the CPU keeps ``(B, N)`` arrays of 3x3 matrices, so its
results stay bit for bit as they were. Here the CPU runs the component-major kernels too: the same substeps
from the same state agree with its own layout to float rounding, and ``particle_array`` reads either layout
back as ``(B, N, 3, 3)``.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_anisompm.backends.taichi_backend import MATRIX_STATE, TaichiBackend
from invphys_anisompm.testing import build_scene

PARTICLE = ("x", "v", "C", "F", "d", "dtil")


def _state(B: int, N: int) -> dict[str, np.ndarray]:
    """A moving, strained, damaged state: every matrix entry distinct, so a transposed or shifted entry shows."""
    rng = np.random.default_rng(0)
    return {"d": rng.uniform(0.0, 0.6, (B, N)), "F": np.eye(3) + 0.05 * rng.standard_normal((B, N, 3, 3)),
            "v": 0.1 * rng.standard_normal((B, N, 3)), "C": rng.standard_normal((B, N, 3, 3))}


def _substeps(component_major: bool, n: int) -> tuple[TaichiBackend, dict[str, np.ndarray]]:
    scene = build_scene(0.0)
    model = scene.model(2).set_material("paste", E=[2e4, 6e4]).set_material("rind", eta=[0.01, 0.05])
    backend = TaichiBackend(scene, 2, arch="cpu", component_major=component_major)
    backend.load(model.table(), model.friction)
    for name, values in _state(2, scene.n_particles).items():
        backend.set_particle_array(name, values)
    nk = max(len(scene.kinematic_names), 1)
    backend.set_frame(np.full(2, 2e-4), np.full(2, n), np.zeros((2, n, nk, 6)), damage_on=True)
    x0 = backend.particle_array("x")
    backend.advance(n)
    backend.sync()
    out = {name: backend.particle_array(name) for name in PARTICLE}
    out["dx"] = out["x"] - x0   # the motion, which is small against the positions themselves
    return backend, out


def test_the_cpu_keeps_matrices_per_particle_and_cuda_would_store_them_component_major():
    scene = build_scene(0.0)
    N = scene.n_particles
    assert TaichiBackend(scene, 2, arch="cpu").F.shape == (2, N)
    backend = TaichiBackend(scene, 2, arch="cpu", component_major=True)
    assert backend.F.shape == (2, 9, N) and backend.C.shape == (2, 9, N)
    values = _state(2, N)["F"].astype(np.float32)
    backend.set_particle_array("F", values)
    assert np.array_equal(backend.particle_array("F"), values)   # read back as (B, N, 3, 3), exactly
    raw = backend.F.to_numpy()
    assert raw[1, 5, 7] == values[1, 7, 1, 2]                     # entry (i, j) of particle p at [b, 3 i + j, p]


def test_component_major_kernels_do_the_same_substeps_as_the_cpu_layout():
    _, ref = _substeps(False, 4)
    _, got = _substeps(True, 4)
    for name in (*PARTICLE, "dx"):
        scale = np.abs(ref[name]).max()
        assert scale > 0, name
        # the same sums in the same order; the compiler may contract them differently (float rounding)
        assert np.abs(got[name] - ref[name]).max() <= 1e-4 * scale, name
    assert np.abs(ref["dx"]).max() > 1e-5   # the particles moved
    for name in MATRIX_STATE:   # the substeps changed the matrices: the comparison covers the kernels' stores
        assert not np.allclose(ref[name], _state(2, ref[name].shape[1])[name], atol=1e-6), name
