"""The Warp backend of the engine, through the orange peel on CPU: selection, parity with Taichi, determinism, errors.

Real simulator runs at the tiny preset (2,112 particles). The Warp module compiles once with the
bundled clang (~5 s, cached in ~/.cache/warp); Taichi compiles its kernels on first use.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("warp")
pytest.importorskip("taichi")

from invphys_orange_peel.features import FEATURE_NAMES, OrangePeelFeatures
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.simulator import OrangePeelSimulator

from invphys.core.errors import DeviceUnavailableError, InvphysError

SPACE = parameter_space()
#: the benchmark's fixed vectors (examples/anisompm/benchmarks/bench_backends.py, seed 0); rows 4, 12, 13, 2
#: are the cheapest at the tiny preset (480-600 substeps) and all of them fracture
BENCH_UNIT = np.random.default_rng(0).uniform(size=(16, SPACE.dim))
FRACTURE_ROWS = [4, 12, 13, 2]


def simulate(backend: str, params: np.ndarray, **cfg) -> list:
    sim = OrangePeelSimulator(backend=backend, preset="tiny", arch="cpu", batch_size=len(params), **cfg)
    return sim.simulate(params)


@pytest.fixture(scope="module")
def fracture_runs() -> dict[str, list]:
    """Both backends on the four cheap benchmark vectors, full tiny preset (120 frames)."""
    params = SPACE.denormalize(BENCH_UNIT[FRACTURE_ROWS])
    return {b: simulate(b, params) for b in ("warp", "taichi")}


def test_elastic_positions_match_taichi() -> None:
    """No damage: after 16 frames (10 of them pulling), positions agree to float32 round-off."""
    params = np.stack([SPACE.center(), SPACE.denormalize(BENCH_UNIT[4])])
    out = {b: simulate(b, params, damage=False, frames=16, record_every=4) for b in ("warp", "taichi")}
    for rw, rt in zip(out["warp"], out["taichi"], strict=True):
        assert rw.ok and rt.ok
        assert rw.stats.backend == "warp" and rw.stats.device.startswith("cpu")
        assert rw.stats.substeps == rt.stats.substeps
        xw, xt = rw.trajectory.positions, rt.trajectory.positions
        assert xw.shape == xt.shape == (5, 2112, 3)
        displacement = np.abs(xt[-1] - xt[0]).max()
        assert displacement > 5e-3  # the gripper really pulled: the comparison is not vacuous
        diff = np.abs(xw - xt).max()
        assert diff / np.abs(xt).max() < 1e-4          # the bar: ~1e-4 relative in positions
        assert diff < 1e-3 * displacement              # and far below the motion itself
        assert float(rw.trajectory.damage.max()) == 0.0


def test_fracture_features_match_taichi(fracture_runs) -> None:
    """With fracture, every feature of four runs agrees to 1e-3 (median) and 3e-2 (worst), relative.

    The issue asks for <= 5% (median); measured over 16 vectors the backends agree to 5e-5 (median)
    and 4.5e-3 (worst, row 2 of these four), see
    ``examples/anisompm/benchmarks/results/backends_cpu_parity.json``. Float32 round-off is amplified where
    cracks form, so the worst-run floor keeps a margin for other CPUs.
    """
    fe = OrangePeelFeatures()
    fw = np.array([fe.extract(r.trajectory) for r in fracture_runs["warp"]])
    ft = np.array([fe.extract(r.trajectory) for r in fracture_runs["taichi"]])
    skin_damage = ft[:, FEATURE_NAMES.index("skin_mean_damage")]
    assert (skin_damage > 0.01).all()  # these runs do fracture
    rel = np.abs(fw - ft) / np.maximum(np.maximum(np.abs(fw), np.abs(ft)), 1e-12)
    med = dict(zip(FEATURE_NAMES, np.median(rel, axis=0), strict=True))
    assert max(med.values()) <= 1e-3, med
    assert rel.max() <= 3e-2, dict(zip(FEATURE_NAMES, rel.max(axis=0), strict=True))
    for rw, rt in zip(fracture_runs["warp"], fracture_runs["taichi"], strict=True):
        assert abs(rw.stats.substeps - rt.stats.substeps) <= 0.02 * rt.stats.substeps


def test_warp_cpu_is_deterministic(fracture_runs) -> None:
    """Identical inputs give bit-identical trajectories (fresh simulator, fresh backend)."""
    again = simulate("warp", SPACE.denormalize(BENCH_UNIT[FRACTURE_ROWS[:2]]))
    for a, b in zip(fracture_runs["warp"][:2], again, strict=True):
        assert a.stats.substeps == b.stats.substeps
        np.testing.assert_array_equal(a.trajectory.positions, b.trajectory.positions)
        np.testing.assert_array_equal(a.trajectory.damage, b.trajectory.damage)


def test_batch_slots_are_independent() -> None:
    """A run gives the same trajectory alone and inside a batch of different runs."""
    p = SPACE.denormalize(BENCH_UNIT[[4, 12]])
    pair = simulate("warp", p, frames=20)
    alone = simulate("warp", p[1:], frames=20)
    np.testing.assert_array_equal(pair[1].trajectory.positions, alone[0].trajectory.positions)
    assert np.abs(pair[0].trajectory.positions - pair[1].trajectory.positions).max() > 1e-4


def test_blow_up_is_reported_like_taichi() -> None:
    """A violated CFL (cfl=10) on a stiff, light material fails with a reason, on both backends."""
    stiff = SPACE.from_mapping({"E": 8000.0, "rho": 0.5, "f_s": 100.0}, defaults=SPACE.to_mapping(SPACE.center()))
    cfg = {"cfl": 10.0, "velocity_cfl": 10.0, "frames": 12}
    rw, = simulate("warp", stiff[None], **cfg)
    rt, = simulate("taichi", stiff[None], **cfg)
    assert not rw.ok and not rt.ok
    assert rw.trajectory is None
    assert rw.failure.split(":")[0] in {"nan", "domain", "energy", "dt"}
    assert rt.failure.split(":")[0] in {"nan", "domain", "energy", "dt"}


def test_cuda_request_without_gpu() -> None:
    """arch='cuda' on a machine without CUDA: a clear error, or CPU when fallback is allowed."""
    from invphys_anisompm.backends.warp_backend import cuda_available

    if cuda_available():
        pytest.skip("a CUDA device is present")
    sim = OrangePeelSimulator(backend="warp", preset="tiny", arch="cuda", frames=1)
    with pytest.raises(DeviceUnavailableError, match="no CUDA GPU"):
        sim.simulate(SPACE.center()[None])
    assert issubclass(DeviceUnavailableError, InvphysError)
    ok = OrangePeelSimulator(backend="warp", preset="tiny", arch="cuda", allow_cpu_fallback=True, frames=1)
    res, = ok.simulate(SPACE.center()[None])
    assert res.ok and res.stats.device.startswith("cpu")


def test_backend_warp_from_spec_block_and_cli(tmp_path) -> None:
    """`backend: warp` in a spec and `invphys simulate --backend warp` select Warp; a typo is located."""
    import invphys
    from invphys import registry
    from invphys.core.errors import SpecError

    text = ("name: warp-tiny\nseed: 0\nstages: [dataset]\n"
            "simulator: {type: orange_peel, preset: tiny, backend: warp, arch: cpu, frames: 2}\n"
            "dataset: {n: 2, batch_size: 2}\n")
    (tmp_path / "spec.yaml").write_text(text)
    spec = invphys.load_spec(tmp_path / "spec.yaml")
    res, = registry.create("simulator", spec.simulator).simulate(SPACE.center()[None])
    assert res.ok and res.stats.backend == "warp"
    (tmp_path / "bad.yaml").write_text(text.replace("backend: warp", "backend: wrap"))
    with pytest.raises(SpecError, match=r"simulator\.backend .*'taichi' or 'warp'"):
        invphys.load_spec(tmp_path / "bad.yaml")
    out = tmp_path / "sim"
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", "simulate", "--simulator", "orange_peel", "--backend", "warp", "--preset", "tiny",
                           "--arch", "cpu", "--config", '{"frames": 3}', "--out", str(out), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    run, = summary["runs"]
    assert run["ok"] and run["stats"]["backend"] == "warp" and run["stats"]["substeps"] > 0
    assert set(run["features"]) == set(FEATURE_NAMES)


def test_warp_grid_mass_and_kernel_times() -> None:
    """P2G deposits exactly the particles' mass; the profiling hook times each stage.

    One run per batch: each run now keeps its own dt, and Warp clears the whole grid every substep,
    so a run that took fewer substeps than its batch-mate shows an empty grid at the end.
    """
    sim = OrangePeelSimulator(backend="warp", preset="tiny", arch="cpu", batch_size=1, frames=12)
    backend = None
    for unit in BENCH_UNIT[[4, 12]]:
        params = SPACE.denormalize(unit[None])
        assert all(r.ok for r in sim.simulate(params))
        backend = sim.engine.backend(1)
        particle_mass = params[:, 1] * 1000.0 * sim.scene.volume * sim.scene.n_particles
        np.testing.assert_allclose(backend.grid_mass(), particle_mass, rtol=1e-4)
    times = backend.kernel_times(2)
    assert set(times) == {"clear", "p2g", "grid", "g2p"} and all(t > 0 for t in times.values())


def test_library_banners_are_quiet_unless_debug() -> None:
    """A normal run prints no Taichi banner/log lines and no Warp CUDA-driver warning; INVPHYS_DEBUG=1 does."""
    import os

    code = ("from invphys_orange_peel.simulator import OrangePeelSimulator as S\n"
            "for b in ('taichi', 'warp'):\n"
            "    s = S(preset='tiny', arch='auto', allow_cpu_fallback=True, frames=1, backend=b)\n"
            "    assert s.simulate(s.parameter_space().center()[None])[0].ok\n"
            "print('done')\n")
    env = {k: v for k, v in os.environ.items() if k != "INVPHYS_DEBUG"}
    quiet = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, env=env)
    assert quiet.returncode == 0, quiet.stderr[-2000:]
    text = quiet.stdout + quiet.stderr
    assert quiet.stdout.strip() == "done"
    assert "[Taichi]" not in text and "[I " not in text and "Warp CUDA warning" not in text, text
    loud = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180,
                          env={**env, "INVPHYS_DEBUG": "1"})
    assert loud.returncode == 0 and "[Taichi]" in loud.stdout + loud.stderr
