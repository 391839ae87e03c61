"""Re-sorting each run's particles into the curve order of their current cells (``taichi_resort.py``).

On the CPU: the Taichi curve keys equal the numpy curves, a sort moves state only (reads unchanged bit
for bit, every run in its own order), whole runs with sorts agree with runs without to float rounding,
and bad settings get one clear error. The speed-up is a GPU figure
(``examples/anisompm/benchmarks/bench_resort.py``). The engine's test scene (``invphys_anisompm.testing``) serves
as the scene; the orange peel only where its config's ``taichi_resort_every`` knob is what is tested.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")
pytest.importorskip("torch")

from invphys_anisompm import Engine
from invphys_anisompm.backends.particle_order import base_cells, hilbert_index, morton_code
from invphys_anisompm.backends.taichi_backend import TaichiBackend, ensure_taichi
from invphys_anisompm.testing import build_scene
from invphys_orange_peel.simulator import OrangePeelSimulator
from pydantic import ValidationError

from invphys.core.errors import InvphysError

SCENE = build_scene(settle_seconds=0.04)
MODEL = SCENE.model(2).set_material("paste", E=[3e4, 6e4], eta=[0.02, 0.05]).set_friction("wire", [0.3, 0.0])


def _by_scene_particle(backend, name: str) -> np.ndarray:
    """Particle array ``name`` with each run's rows in the scene's order (device particle p is sid[b, p])."""
    values, sid = backend.particle_array(name), backend.particle_array("sid")
    out = np.empty_like(values)
    for b in range(values.shape[0]):
        out[b, sid[b]] = values[b]
    return out


def _sim(**kw) -> OrangePeelSimulator:
    return OrangePeelSimulator(backend="taichi", preset="tiny", arch="cpu", batch_size=2, frames=8, **kw)


@pytest.mark.parametrize("curve", ["hilbert", "morton"])
def test_curve_keys_equal_the_numpy_curves(curve):
    import torch
    from invphys_anisompm.backends.taichi_resort import _build_resort_kernels

    ensure_taichi("cpu")
    grid, dx = 40, 0.025
    cells = np.random.default_rng(0).integers(0, grid - 2, size=(2, 500, 3))
    x = ((cells + 0.5 + 0.3) * dx).astype(np.float32)            # inside each cell's base range
    assert np.array_equal(base_cells(x.reshape(-1, 3), dx, grid).reshape(cells.shape), cells)
    keys_kernel, _ = _build_resort_kernels(grid, curve)
    xs = torch.from_numpy(x)
    keys = torch.zeros((2, 500), dtype=torch.int64)
    keys_kernel(1.0 / dx, xs, keys)
    bits = grid.bit_length()
    want = hilbert_index if curve == "hilbert" else morton_code
    assert np.array_equal(keys.numpy(), want(cells.reshape(-1, 3), bits).reshape(2, 500))


@pytest.mark.parametrize("component_major", [False, True], ids=["matrices_aos", "matrices_component_major"])
def test_a_sort_moves_state_only_and_puts_each_run_in_the_order_of_its_cells(component_major):
    scene = SCENE
    backend = TaichiBackend(scene, 2, arch="cpu", particle_order="hilbert", resort_every=10_000,
                            component_major=component_major)
    backend.load(MODEL.table(), MODEL.friction)
    N, o = scene.n_particles, scene.options
    rng = np.random.default_rng(1)
    x = backend.x.to_numpy() + rng.normal(0.0, 3 * o.dx, size=(2, N, 3)).astype(np.float32)  # each run its own
    d = rng.uniform(size=(2, N)).astype(np.float32)
    backend.x.from_numpy(np.clip(x, 2 * o.dx, o.domain - 2 * o.dx))
    backend.d.from_numpy(d)
    backend.set_particle_array("F", np.eye(3) + rng.normal(0.0, 0.1, size=(2, N, 3, 3)))  # each particle its own
    backend.set_particle_array("C", rng.normal(size=(2, N, 3, 3)))
    before_x, before_d = backend.read()
    before = {name: _by_scene_particle(backend, name) for name in ("F", "C", "v")}
    backend.resorter.sort()
    after_x, after_d = backend.read()
    assert np.array_equal(after_x, before_x) and np.array_equal(after_d, before_d)
    sid = backend.sid.to_numpy()
    bits = int(o.grid).bit_length()
    for b in range(2):
        assert np.array_equal(np.sort(sid[b]), np.arange(N))                 # a permutation of the scene
        keys = hilbert_index(base_cells(backend.x.to_numpy()[b], o.dx, o.grid), bits)
        assert np.all(np.diff(keys) >= 0)                                      # in the curve order of now
    assert not np.array_equal(sid[0], sid[1])                                  # each run sorted by its own cells
    # the per-particle state travelled with its particle, every entry of the component-major matrices
    for name, values in before.items():
        assert np.array_equal(_by_scene_particle(backend, name), values), name
    assert backend.resorter.sorts == 1


def test_whole_runs_with_resorting_agree_with_runs_without():
    plain = Engine(SCENE, backend="taichi", arch="cpu", p2g="atomic", resort_every=0).run(MODEL, 4, 2)
    engine = Engine(SCENE, backend="taichi", arch="cpu", p2g="atomic", resort_every=16)
    sorted_ = engine.run(MODEL, 4, 2)
    backend = engine.backend(2)
    assert backend.particle_order == "hilbert" and backend.resorter.sorts > 0
    for a, b in zip(plain, sorted_, strict=True):
        assert a.ok and b.ok and a.substeps == b.substeps
        assert len(a.positions) == len(b.positions) == 3
        moved = max(np.abs(x - a.positions[0]).max() for x in a.positions)
        assert moved > 1e-3   # the wire cut, the grip pulled: the comparison is not vacuous
        # the same physics summed in another particle order (float rounding only)
        for xa, xb, da, db in zip(a.positions, b.positions, a.damage, b.damage, strict=True):
            assert np.abs(xa - xb).max() < 1e-4
            assert np.abs(da - db).max() < 1e-3


def test_the_simulators_resort_knob_reaches_the_backend():
    """A food's ``taichi_resort_every`` (the orange peel's config) sets the backend's re-sorting."""
    sim = _sim(taichi_p2g="atomic", taichi_resort_every=16)
    backend = sim.engine.backend(2)
    assert backend.resort_every == 16 and backend.particle_order == "hilbert"
    assert _sim().engine.backend(2).resort_every == 0   # the CPU default: never


def test_bad_resort_settings_get_one_clear_error():
    scene = SCENE
    with pytest.raises(InvphysError, match="resort_every must be"):
        TaichiBackend(scene, 1, arch="cpu", resort_every=-1)
    with pytest.raises(InvphysError, match="needs a particle_order curve"):
        TaichiBackend(scene, 1, arch="cpu", particle_order="scene", resort_every=8)
    with pytest.raises(ValidationError):
        _sim(taichi_resort_every=-3)
    assert TaichiBackend(scene, 1, arch="cpu").resorter is None              # the CPU default: never


def test_without_pytorch_the_default_is_never_and_asking_for_sorts_says_so(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a))
    scene = SCENE
    assert TaichiBackend(scene, 1, arch="cpu", particle_order="hilbert").resorter is None
    with pytest.raises(InvphysError, match="needs PyTorch"):
        TaichiBackend(scene, 1, arch="cpu", particle_order="hilbert", resort_every=8)
