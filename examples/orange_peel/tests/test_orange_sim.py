"""The orange-peel simulator (Taichi backend, CPU) at the tiny preset: real runs, real physics checks.

Cost: the module shares one batched simulation of three parameter vectors (~840 substeps), plus
short runs (a few frames) for the checks that need no peeling.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("taichi")

from invphys_orange_peel.features import FEATURE_NAMES, OrangePeelFeatures
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.presets import PRESETS, UnknownPresetError, get_preset
from invphys_orange_peel.scene import build_scene
from invphys_orange_peel.simulator import OrangePeelSimulator

from invphys.core.errors import DeviceUnavailableError, ParameterRangeError

SPACE = parameter_space()
EX = OrangePeelFeatures()


def _with(**values: float) -> np.ndarray:
    return SPACE.from_mapping(values, defaults=SPACE.to_mapping(SPACE.center()))


@pytest.fixture(scope="module")
def sweep():
    """Centre, weak skin (sigma_s = 0.05) and strong skin (sigma_s = 0.5), one batch, full tiny run."""
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=3)
    params = np.stack([SPACE.center(), _with(sigma_s=0.05), _with(sigma_s=0.5)])
    results = sim.simulate(params)
    return sim, params, results


def test_batch_runs_and_records(sweep) -> None:
    sim, params, results = sweep
    assert len(results) == 3
    for res, p in zip(results, params, strict=True):
        assert res.ok, res.failure
        np.testing.assert_array_equal(res.params, p)
        t = res.trajectory
        assert t.positions.shape == (25, 2112, 3) and t.damage.shape == (25, 2112)
        assert list(t.frame_indices) == list(range(0, 121, 5))
        assert set(np.unique(t.labels)) == {0, 1}
        st = res.stats
        assert st.backend == "taichi" and st.device.startswith("cpu") and st.preset == "tiny"
        assert st.simulator == "orange_peel" and st.simulator_version == sim.version
        # substeps: at least the dt cap, at least the elastic CFL count (here the CFL binds)
        assert st.substeps >= 120 * 4
        assert st.wall_time_s > 0
        assert t.extra["gripper_path"].shape == (25, 3)
        for key in ("frame_separation", "frame_mean_damage", "frame_work"):
            assert t.extra[key].shape == (121,) and np.isfinite(t.extra[key]).all()
        # the run's own dt: elastic CFL, frame cap and 0.1 min(eta) (the damage rate is resolved)
        eta = min(res.params[SPACE.names.index("eta_s")], res.params[SPACE.names.index("eta_i")])
        assert t.extra["dt"] <= 0.1 * eta + 1e-12 and t.extra["guard_frames"] == 0
        assert st.substeps == t.extra["settle_substeps"] + 120 * round(1 / 12 / t.extra["dt"])


def test_skin_peels_away_along_the_arc(sweep) -> None:
    """Centre of the space: the gripped skin follows the arc and skin separates from the flesh."""
    _, _, results = sweep
    t = results[0].trajectory
    grip = t.extra["gripped"]
    end = t.extra["gripper_path"][-1]
    start = t.extra["gripper_path"][0]
    moved = t.positions[-1][grip].mean(0) - t.positions[0][grip].mean(0)
    np.testing.assert_allclose(moved, end - start, atol=1e-4)
    f = dict(zip(FEATURE_NAMES, EX.extract(t), strict=True))
    assert f["skin_detachment_fraction"] > 0.01
    assert f["skin_mean_damage"] > 0.05
    assert f["fracture_onset_frame"] < 120


def test_weaker_skin_damages_more_and_fractures_no_later(sweep) -> None:
    _, _, results = sweep
    feats = [dict(zip(FEATURE_NAMES, EX.extract(r.trajectory), strict=True)) for r in results]
    centre, weak, strong = feats
    assert weak["skin_mean_damage"] > centre["skin_mean_damage"] > strong["skin_mean_damage"]
    # the weakest skin starts to fracture earlier
    assert weak["fracture_onset_frame"] < centre["fracture_onset_frame"]
    assert weak["fracture_onset_frame"] < strong["fracture_onset_frame"]
    assert weak["skin_detachment_fraction"] > strong["skin_detachment_fraction"]


def test_engine_simulator_reproduces_the_orange_peels_own_kernels(sweep) -> None:
    """The sweep's three runs are rows 0-2 of the reference made before the port onto the engine."""
    from test_orange_engine_parity import assert_matches_reference

    _, _, results = sweep
    assert_matches_reference(results, "taichi", [0, 1, 2])


def test_damage_never_decreases_and_stays_in_unit_interval(sweep) -> None:
    _, _, results = sweep
    for res in results:
        d = res.trajectory.damage
        assert d.min() >= 0.0 and d.max() <= 1.0
        assert (np.diff(d, axis=0) >= 0).all()


def test_cpu_runs_are_bit_identical_across_calls_and_batches(sweep) -> None:
    """The centre run alone, in a new simulator, repeats the batched centre run exactly."""
    _, params, results = sweep
    again = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=1).simulate(params[:1])[0]
    np.testing.assert_array_equal(again.trajectory.positions, results[0].trajectory.positions)
    np.testing.assert_array_equal(again.trajectory.damage, results[0].trajectory.damage)
    np.testing.assert_array_equal(EX.extract(again.trajectory), EX.extract(results[0].trajectory))
    assert again.stats.substeps == results[0].stats.substeps


def test_real_trajectories_through_shared_memory_give_the_in_process_features(sweep) -> None:
    """The extraction pool's shared-memory hand-off on real orange-peel trajectories (forced on: tiny ones are
    below its 1 MiB default): the features of in-process extraction, bit for bit."""
    from invphys.plugins.executors._extract_pool import ExtractionPool

    _, _, results = sweep
    with ExtractionPool(OrangePeelFeatures(), 2, min_shared_bytes=0) as pool:
        futures = [pool.extract(r.trajectory) for r in results]
        got = [f.result() for f in futures]
        assert pool._blocks.created >= 1
    for r, feats in zip(results, got, strict=True):
        np.testing.assert_array_equal(feats, EX.extract(r.trajectory))


def test_mass_is_conserved_on_the_grid() -> None:
    """After a pulling frame, P2G deposits exactly the particles' total mass (partition of unity)."""
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=2, frames=24)
    params = np.stack([SPACE.center(), _with(rho=10.0)])
    results = sim.simulate(params)
    assert all(r.ok for r in results)
    backend = sim.engine.backend(2)
    grid_mass = backend.grid_mass()
    particle_mass = params[:, 1] * 1000.0 * sim.scene.volume * sim.scene.n_particles
    # sorted into the batch by dt: compare as sets
    np.testing.assert_allclose(np.sort(grid_mass), np.sort(particle_mass), rtol=1e-4)


def test_e_and_rho_are_told_apart() -> None:
    """(E, rho) and (2E, 2rho) have the same E/rho, hence the same motion (also with gravity: every term
    of the momentum balance scales with it); the gripper's work tells them apart (it scales with both)."""
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=2, frames=36)
    params = np.stack([_with(E=500.0, rho=2.0), _with(E=1000.0, rho=4.0)])
    a, b = (dict(zip(FEATURE_NAMES, EX.extract(r.trajectory), strict=True)) for r in sim.simulate(params))
    assert a["peeling_work"] > -3  # the gripper did pull
    assert b["peeling_work"] - a["peeling_work"] == pytest.approx(np.log10(2.0), abs=0.01)
    assert a["final_separation"] == pytest.approx(b["final_separation"], rel=1e-3)


def test_settling_sags_under_gravity_with_damage_frozen() -> None:
    """Frame 0 is the settled state: the orange sagged, no damage grew, the gripped patch stayed put."""
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=1, frames=1, record_every=1)
    [res] = sim.simulate(_with(E=50.0, sigma_s=0.05, sigma_i=0.1)[None])
    t = res.trajectory
    drop = sim.scene.positions[:, 1] - t.positions[0][:, 1]
    assert drop.max() > 0.2 * sim.scene.dx and t.extra["settle_substeps"] > 0
    assert float(t.damage[0].max()) == 0.0
    np.testing.assert_allclose(t.positions[0][sim.scene.gripped], sim.scene.positions[sim.scene.gripped], atol=1e-6)
    assert float(t.damage[1].max()) > 0.0  # weak material: damage starts as soon as settling ends


def test_no_damage_and_no_motion_without_load() -> None:
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=1, gripper=False, gravity=0.0, frames=12)
    [res] = sim.simulate(_with(sigma_s=0.05, sigma_i=0.1)[None])
    assert res.ok
    assert float(res.trajectory.damage.max()) == 0.0
    assert float(np.abs(res.trajectory.positions[-1] - res.trajectory.positions[0]).max()) < 1e-6
    f = dict(zip(FEATURE_NAMES, EX.extract(res.trajectory), strict=True))
    assert all(np.isfinite(list(f.values())))
    assert f["fracture_onset_frame"] == 2 * 12  # never fractures: extrapolated to twice the run
    assert f["separation_half_time"] == 12       # no separation: the last frame
    assert f["skin_detachment_fraction"] == 0.0 and f["skin_mean_damage"] == 0.0


def test_blow_up_is_reported_as_failure_with_reason() -> None:
    """A CFL number of 8 makes the explicit scheme unstable: the run fails with a reason, others go on."""
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=1, cfl=8.0, min_substeps_per_frame=1,
                              frames=40)
    [res] = sim.simulate(_with(E=8000.0, rho=0.5, f_s=100.0)[None])
    assert not res.ok
    assert res.trajectory is None and res.features is None
    assert res.failure.split(":")[0] in {"nan", "energy", "domain", "dt"}
    assert "frame" in res.failure
    assert res.stats.substeps > 0


def test_out_of_range_parameter_names_it_and_its_range() -> None:
    sim = OrangePeelSimulator(preset="tiny", arch="cpu")
    bad = SPACE.center().copy()
    bad[SPACE.names.index("sigma_i")] = 0.95
    with pytest.raises(ParameterRangeError, match=r"sigma_i = 0\.95 is outside its range \[0\.1, 0\.9\]"):
        sim.simulate(bad[None])
    too_stiff = SPACE.center().copy()
    too_stiff[0] = 9000.0
    with pytest.raises(ParameterRangeError, match=r"E = 9000 is outside its range \[50, 8000\] Pa"):
        sim.simulate(np.stack([SPACE.center(), too_stiff]))


def test_device_and_launch_batching_are_not_part_of_a_run() -> None:
    """Rows made on another device or in other batches are the same stored rows; another frame count is not
    (the simulator's ``identity_ignores``; the store side: tests/test_dataset_process_workers.py)."""
    from invphys.core.dataset import RunIdentity

    block = {"preset": "tiny", "arch": "cpu", "batch_size": 2, "frames": 48}
    config = RunIdentity.of(OrangePeelSimulator(**block)).config
    assert RunIdentity.of(OrangePeelSimulator(**{**block, "arch": "auto", "batch_size": 8})).config == config
    assert RunIdentity.of(OrangePeelSimulator(**{**block, "frames": 47})).config != config


def test_unknown_preset_suggests_the_closest() -> None:
    with pytest.raises(UnknownPresetError, match="Did you mean 'tiny'"):
        get_preset("tiyn")
    with pytest.raises(Exception, match="Did you mean 'quick'"):
        OrangePeelSimulator(preset="quik")


def test_cuda_without_gpu_is_a_clear_error() -> None:
    from invphys_anisompm.backends.taichi_backend import cuda_available, ensure_taichi

    if cuda_available():
        pytest.skip("a CUDA GPU is present")
    with pytest.raises(DeviceUnavailableError, match="allow_cpu_fallback"):
        ensure_taichi("cuda")
    assert ensure_taichi("cuda", allow_cpu_fallback=True) == "cpu"


def test_presets_have_the_documented_sizes() -> None:
    sizes = {name: build_scene(p).n_particles for name, p in PRESETS.items()}
    assert 45_000 <= sizes["paper"] <= 55_000
    assert 5_000 <= sizes["quick"] <= 10_000
    assert 1_000 <= sizes["tiny"] <= 3_000
    scene = build_scene(PRESETS["paper"])
    skin = scene.labels == 0
    assert np.allclose(np.linalg.norm(scene.fibres[skin], axis=1), 1.0)
    assert np.allclose(scene.fibres[~skin], 0.0)
    # fibres are tangent to the dome
    radial = scene.positions[skin] - scene.centre
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.abs(np.sum(radial * scene.fibres[skin], axis=1)).max() < 1e-6
    assert PRESETS["paper"].frames == 240


def test_taichi_is_initialised_once_and_refuses_another_arch(monkeypatch) -> None:
    from invphys_anisompm.backends import taichi_backend as tb

    from invphys.core.errors import InvphysError

    assert tb.ensure_taichi("cpu") == "cpu"          # already initialised by the runs above: free
    assert tb.ensure_taichi("auto") == "cpu"
    monkeypatch.setattr(tb, "cuda_available", lambda: True)
    with pytest.raises(InvphysError, match=r"already initialised on 'cpu'.*cannot switch to 'cuda'"):
        tb.ensure_taichi("cuda")


def test_plugins_conform_and_register_through_the_entry_point() -> None:
    from invphys.registry import Registry
    from invphys.testing import check_feature_extractor, check_plugin_class, check_simulator

    check_plugin_class(OrangePeelSimulator)
    check_plugin_class(OrangePeelFeatures)
    reg = Registry(autoload=True)
    assert reg.get("simulator", "orange_peel") is OrangePeelSimulator
    assert reg.get("feature_extractor", "orange_peel_features") is OrangePeelFeatures
    sim = reg.create("simulator", {"type": "orange_peel", "preset": "tiny", "arch": "cpu", "frames": 6,
                                   "batch_size": 2})
    results = check_simulator(sim, n_runs=2)
    y = check_feature_extractor(OrangePeelFeatures(), results)
    assert y.shape == (2, 12)


def test_plugin_modules_do_not_import_taichi_or_warp() -> None:
    import subprocess
    import sys

    code = ("import sys, invphys_orange_peel.plugin, invphys_orange_peel.simulator, "
            "invphys_orange_peel.features, invphys_orange_peel.render\n"
            "heavy = [m for m in ('taichi', 'warp', 'torch') if m in sys.modules]\n"
            "assert not heavy, heavy")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
