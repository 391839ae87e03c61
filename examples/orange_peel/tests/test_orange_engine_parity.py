"""The orange peel on the AnisoMPM engine reproduces the orange peel's own kernels (before the port).

`data/orange_peel_reference_tiny.npz` (beside this file) holds the 12 features, substeps and per-frame
series of seven tiny-preset runs made on the CPU by the orange peel's own Taichi and Warp kernels (simulator
0.2.0, commit in the file; `data/make_orange_reference.py`). The engine-based simulator must give the same
substeps and the same features to float32 round-off amplified by fracture. The stored features are in
0.2.0's linear units; 0.3.0 reports four of them in log10 (`log_units`, the physics is unchanged), so the
reference is converted with that function and those four are compared by their difference in log10, which
is the relative difference of the linear statistic (times 1/ln 10). Taichi is checked on three of
the rows in `test_orange_sim.py` (its module-wide simulation); Warp here on two rows (~10 s).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from invphys_orange_peel.features import FEATURE_NAMES, LOG_OFFSETS, OrangePeelFeatures, log_units
from invphys_orange_peel.presets import get_preset
from invphys_orange_peel.scene import build_scene

REFERENCE = Path(__file__).parent / "data" / "orange_peel_reference_tiny.npz"


def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE, allow_pickle=False) as ref:
        return {k: ref[k] for k in ref.files}


def assert_matches_reference(results: list, backend: str, rows: list[int]) -> None:
    """Substeps equal, every feature within 5e-3 relative (median 1e-4), series to round-off."""
    ref = reference()
    assert tuple(ref["feature_names"]) == FEATURE_NAMES
    np.testing.assert_array_equal(ref["params"][rows], np.stack([r.params for r in results]))
    ext = OrangePeelFeatures()
    got = np.stack([ext.extract(r.trajectory) for r in results])
    baseline = build_scene(get_preset("tiny")).separation()
    assert all(r.trajectory.extra["scene_separation"] == baseline for r in results)
    want = np.stack([log_units(v, baseline) for v in ref[f"{backend}_features"][rows]])
    assert [r.stats.substeps for r in results] == list(ref[f"{backend}_substeps"][rows])
    rel = np.abs(got - want) / np.maximum(np.abs(want), 1e-12)
    logged = [FEATURE_NAMES.index(name) for name in LOG_OFFSETS]
    rel[:, logged] = np.abs(got - want)[:, logged] * np.log(10.0)  # relative difference of the linear value
    assert np.median(rel) <= 1e-4, dict(zip(FEATURE_NAMES, np.median(rel, axis=0), strict=True))
    assert rel.max() <= 5e-3, dict(zip(FEATURE_NAMES, rel.max(axis=0), strict=True))
    for key, atol in (("frame_separation", 1e-5), ("frame_mean_damage", 1e-3), ("frame_work", 1e-4)):
        series = np.stack([r.trajectory.extra[key] for r in results])
        np.testing.assert_allclose(series, ref[f"{backend}_{key}"][rows], atol=atol, err_msg=key)
    moved = np.abs(ref[f"{backend}_final_positions"][rows] - results[0].trajectory.positions[0]).max()
    assert moved > 1e-2  # the runs really peel: the comparison is not vacuous
    final = np.stack([r.trajectory.positions[-1] for r in results])
    assert np.abs(final - ref[f"{backend}_final_positions"][rows]).max() < 1e-3 * moved


def test_warp_on_the_engine_reproduces_the_reference() -> None:
    pytest.importorskip("warp")
    from invphys_orange_peel.simulator import OrangePeelSimulator

    rows = [0, 1]
    sim = OrangePeelSimulator(backend="warp", preset="tiny", arch="cpu", batch_size=2)
    results = sim.simulate(reference()["params"][rows])
    assert all(r.ok for r in results)
    assert results[0].stats.backend == "warp"
    assert_matches_reference(results, "warp", rows)


def test_continuous_batching_gives_the_lockstep_results() -> None:
    """The engine's continuous batching serves the orange too: same features as lock-step batches."""
    pytest.importorskip("warp")
    from invphys_orange_peel.simulator import OrangePeelSimulator

    params = reference()["params"][[0, 1]]
    lock = OrangePeelSimulator(backend="warp", preset="tiny", arch="cpu", batch_size=2, frames=24)
    cont = OrangePeelSimulator(backend="warp", preset="tiny", arch="cpu", batch_size=1, frames=24,
                               scheduling="continuous")
    assert cont.native_stream and not lock.native_stream
    ext = OrangePeelFeatures()
    a = [ext.extract(r.trajectory) for r in lock.simulate(params)]
    b = {i: ext.extract(r.trajectory) for i, r in cont.simulate_stream(params)}
    assert sorted(b) == [0, 1]
    for i in range(2):
        np.testing.assert_allclose(b[i], a[i], rtol=1e-5, atol=1e-7)
    from invphys.core.dataset import RunIdentity

    assert RunIdentity.of(lock) == RunIdentity.of(cont)  # scheduling is not part of a run's identity


def test_queue_order_leaves_every_rows_features_unchanged() -> None:
    """Continuous batching in either queue order (and lock-step) gives each row bit-identical features on
    the CPU: a run's result does not depend on its slot, its start time or the runs beside it."""
    from invphys_orange_peel.simulator import OrangePeelSimulator

    params = reference()["params"][[0, 3, 5]]   # 162, 324 and 468 substeps over 12 frames
    ext = OrangePeelFeatures()
    feats, finish = {}, {}
    for order in ("longest_first", "given"):
        sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=2, frames=12, scheduling="continuous",
                                  queue_order=order, min_chunk=2)
        stream = list(sim.simulate_stream(params))
        finish[order] = [i for i, _ in stream]
        feats[order] = {i: ext.extract(r.trajectory) for i, r in stream}
    cost = sim.engine.estimate_cost(sim_model(sim, params), sim.frames)
    assert len(set(cost)) == 3, "the rows must differ in cost for the order to matter"
    assert finish["longest_first"] != finish["given"]
    lock = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=3, frames=12)
    plain = lock.simulate(params)
    for i in range(3):
        np.testing.assert_array_equal(feats["longest_first"][i], feats["given"][i])
        np.testing.assert_array_equal(feats["given"][i], ext.extract(plain[i].trajectory))
    from invphys.core.dataset import RunIdentity

    assert RunIdentity.of(sim) == RunIdentity.of(lock)   # neither setting is part of a run's identity


def sim_model(sim, params):
    from invphys_orange_peel.engine_scene import model_for

    return model_for(sim.engine_scene, params)


def test_defaults_are_continuous_batches_of_64_on_cuda_and_lockstep_16_on_the_cpu():
    from invphys_orange_peel.simulator import OrangePeelSimulator

    # resolved from the config alone (arch "cuda" is not probed: no engine, no GPU needed)
    gpu = OrangePeelSimulator(preset="tiny", arch="cuda")
    assert (gpu.scheduling, gpu.min_chunk, gpu.native_stream, gpu.batch_size) == ("continuous", 64, True, 64)
    warp = OrangePeelSimulator(preset="tiny", arch="cuda", backend="warp")
    assert (warp.scheduling, warp.batch_size) == ("lockstep", 16)     # the defaults measured for Taichi only
    cpu = OrangePeelSimulator(preset="tiny", arch="cpu")
    assert (cpu.scheduling, cpu.min_chunk, cpu.native_stream, cpu.batch_size) == ("lockstep", 1, False, 16)
    chosen = OrangePeelSimulator(preset="tiny", arch="cuda", scheduling="lockstep", min_chunk=4, batch_size=8)
    assert (chosen.scheduling, chosen.min_chunk, chosen.batch_size) == ("lockstep", 4, 8)
    # "auto" here probes the machine: this test machine has no CUDA GPU
    from invphys_anisompm.backends.taichi_backend import cuda_available

    assert OrangePeelSimulator(preset="tiny", arch="auto").scheduling == ("continuous" if cuda_available() else "lockstep")
    fallback = OrangePeelSimulator(preset="tiny", arch="cuda", allow_cpu_fallback=True)   # probed as "auto" is
    assert fallback.batch_size == (64 if cuda_available() else 16)


def test_recorded_frames_are_gathered_into_the_orange_order_as_the_stacked_reorder_gives():
    from invphys_orange_peel.simulator import OrangePeelSimulator

    es = OrangePeelSimulator(preset="tiny", arch="cpu").engine_scene
    n = len(es.from_engine)
    assert sorted(es.from_engine.tolist()) == list(range(n)) and not np.array_equal(es.from_engine, np.arange(n))
    rng = np.random.default_rng(0)
    for shape, dtype in (((n, 3), np.float32), ((n,), np.float32), ((n, 3), np.float64)):
        frames = [rng.normal(size=shape).astype(dtype) for _ in range(4)]
        got = es.frames_in_orange_order(frames)
        want = np.take(np.stack(frames), es.from_engine, axis=1).astype(np.float32)   # stack, reorder, cast
        assert got.dtype == np.float32 and got.shape == (4, *shape)
        np.testing.assert_array_equal(got, want)
        orange_particle = int(es.to_engine[7])   # engine particle 7 is this orange particle
        np.testing.assert_array_equal(got[2, orange_particle], frames[2][7].astype(np.float32))
    with pytest.raises(ValueError, match="no recorded frames"):
        es.frames_in_orange_order([])
    with pytest.raises(ValueError, match="frame 1 has shape"):
        es.frames_in_orange_order([np.zeros((n, 3), np.float32), np.zeros((n,), np.float32)])
