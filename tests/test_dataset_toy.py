"""A small real simulator for the dataset tests: damped harmonic oscillators, integrated explicitly.

``ToyOscillator`` integrates ``m x'' = -k x - c x'`` for a few particles with semi-implicit Euler, a
batch at a time (vectorised over the batch). Like an explicit MPM code it blows up when the step is
too long for the stiffness (``omega dt > 2``) and reports that run as failed. Test hooks make rows
raise an exception or kill their process (``raise_c_above``, ``crash_c_above``) and slow runs down
(``sleep_s``). The module is importable by worker processes as ``test_dataset_toy:ToyOscillator`` when
``tests/`` is on the path (pytest puts it there; subprocesses get it through PYTHONPATH).
"""

from __future__ import annotations

import os
import time
from types import SimpleNamespace
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from invphys.core.interfaces import FeatureExtractor, PluginConfig, Simulator
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.results import RunStats, SimulationResult, Trajectory

SIM = "test_dataset_toy:ToyOscillator"
FEATURES = "test_dataset_toy:ToyFeatures"
STREAMING = "test_dataset_toy:StreamingOscillator"


class ToyOscillator(Simulator):
    """Damped oscillators (stiffness k, damping c, mass m), semi-implicit Euler, batched with NumPy."""

    name = "toy_oscillator"
    version = "1"

    class Config(PluginConfig):
        preset: Literal["tiny"] = "tiny"
        backend: Literal["numpy"] = "numpy"
        n_particles: int = Field(4, ge=1)
        n_frames: int = Field(40, ge=2)
        fps: float = Field(20.0, gt=0)
        substeps: int = Field(2, ge=1, description="integration steps per frame")
        sleep_s: float = Field(0.0, ge=0, description="extra wall time per row (tests)")
        raise_c_above: float | None = Field(None, description="rows with damping c above this raise")
        crash_c_above: float | None = Field(None, description="rows with damping c above this kill the process")

    def parameter_space(self) -> ParameterSpace:
        return ParameterSpace((Parameter("k", 1.0, 1e4, log=True, unit="N/m"),
                               Parameter("c", 0.01, 1.0, log=True, unit="N s/m"),
                               Parameter("m", 0.5, 2.0, unit="kg")))

    def default_feature_extractor(self) -> str | None:
        return FEATURES

    def simulate(self, params, on_result=None):
        cfg = self.config
        p = np.atleast_2d(self.parameter_space().check(params))
        if cfg.crash_c_above is not None and (p[:, 1] > cfg.crash_c_above).any():
            os._exit(17)
        if cfg.raise_c_above is not None and (p[:, 1] > cfg.raise_c_above).any():
            raise RuntimeError(f"toy oscillator exploded at c = {p[:, 1].max():.4g}")
        t0 = time.perf_counter()
        k, c, m = (p[:, j:j + 1] for j in range(3))
        b, n = len(p), cfg.n_particles
        x = np.tile(np.linspace(0.5, 1.0, n), (b, 1))
        v = np.zeros((b, n))
        dt = 1.0 / (cfg.fps * cfg.substeps)
        frames = np.empty((cfg.n_frames, b, n))
        energy0 = 0.5 * k * x * x
        energy = np.empty((cfg.n_frames, b, n))
        blown = np.zeros(b, dtype=bool)
        for f in range(cfg.n_frames):
            for _ in range(cfg.substeps):
                v += dt * (-k * x - c * v) / m
                x += dt * v
            frames[f], energy[f] = x, 0.5 * k * x * x + 0.5 * m * v * v
            blown |= ~np.isfinite(x).all(axis=1) | (np.abs(x) > 1e3).any(axis=1)
        if cfg.sleep_s:
            time.sleep(cfg.sleep_s * b)
        wall = (time.perf_counter() - t0) / b
        results = []
        for i in range(b):
            stats = RunStats(substeps=cfg.n_frames * cfg.substeps, wall_time_s=wall, backend="numpy",
                             device="cpu", preset=cfg.preset, simulator=self.name, simulator_version=self.version)
            if blown[i]:
                res = SimulationResult(params=p[i], ok=False, stats=stats,
                                       failure="blow-up: |x| > 1e3 (omega dt > 2, step too long)")
            else:
                pos = np.zeros((cfg.n_frames, n, 3), dtype=np.float32)
                pos[:, :, 0] = frames[:, i]
                damage = np.clip(1.0 - energy[:, i] / energy0[i], 0.0, 1.0).astype(np.float32)
                traj = Trajectory(positions=pos, damage=damage, labels=np.zeros(n, dtype=np.int8),
                                  frame_indices=np.arange(cfg.n_frames), fps=cfg.fps)
                res = SimulationResult(params=p[i], ok=True, stats=stats, trajectory=traj)
            if on_result is not None:
                on_result(i, res)
            results.append(res)
        return results


class StreamingOscillator(ToyOscillator):
    """The toy oscillator with a stream of its own (``native_stream``), as a simulator on a warm engine has:
    it notes how many rows each stream call gets (``streams``, this process), hands the results back last row
    first (an engine hands them back as runs finish) and counts the substeps it ran in
    ``_engine.counters.useful`` (where executors read a warm engine's slot counters)."""

    name = "streaming_oscillator"
    native_stream = True
    streams: ClassVar[list[int]] = []

    def __init__(self, config=None, **settings) -> None:
        super().__init__(config, **settings)
        self._engine = SimpleNamespace(counters=SimpleNamespace(useful=0, launched=0))

    def simulate_stream(self, params, batch_size=None):
        type(self).streams.append(len(params))
        results = self.simulate(params)
        for i in reversed(range(len(results))):
            self._engine.counters.useful += results[i].stats.substeps
            self._engine.counters.launched += results[i].stats.substeps
            yield i, results[i]


class ToyFeatures(FeatureExtractor):
    """Amplitude, decay, oscillation rate and dissipated energy of oscillator trajectories."""

    name = "toy_oscillator_features"

    class Config(PluginConfig):
        pass

    @property
    def feature_names(self) -> tuple[str, ...]:
        return ("peak_abs", "final_abs", "log_decay", "crossings_per_s", "final_damage")

    def extract(self, trajectory: Trajectory) -> np.ndarray:
        x = trajectory.positions[:, :, 0].astype(np.float64)
        half = len(x) // 2
        first, second = np.abs(x[:half]).max(), np.abs(x[half:]).max()
        crossings = (np.diff(np.sign(x), axis=0) != 0).sum(axis=0).mean()
        duration = trajectory.n_frames / trajectory.fps
        return np.array([np.abs(x[1:]).max(), np.abs(x[-1]).mean(),
                         np.log((second + 1e-12) / (first + 1e-12)), crossings / duration,
                         float(trajectory.damage[-1].mean())])


# ----------------------------------------------------------------------------------------------
# The toy plugin's own checks (so that the dataset tests stand on a simulator that works)
# ----------------------------------------------------------------------------------------------
def test_toy_oscillator_is_deterministic_batched_and_detects_blow_up() -> None:
    sim, ext = ToyOscillator(substeps=1), ToyFeatures()
    space = sim.parameter_space()
    params = space.denormalize(np.array([[0.2, 0.5, 0.5], [0.99, 0.0, 0.0], [0.5, 0.9, 1.0]]))
    batch = sim.simulate(params)
    single = [sim.simulate(p[None])[0] for p in params]
    assert [r.ok for r in batch] == [True, False, True]  # k = 9e3 N/m, m = 0.5 kg: omega dt = 2.7 > 2
    assert "blow-up" in batch[1].failure
    for a, b in zip(batch, single, strict=True):
        if a.ok:
            np.testing.assert_array_equal(ext.extract(a.trajectory), ext.extract(b.trajectory))
    f = ext.extract(batch[0].trajectory)
    assert f.shape == (5,) and np.isfinite(f).all()
    # more damping decays faster
    light, heavy = space.denormalize(np.array([[0.3, 0.1, 0.5], [0.3, 0.95, 0.5]]))
    fl, fh = (ext.extract(r.trajectory) for r in sim.simulate(np.stack([light, heavy])))
    assert fh[2] < fl[2]


def test_toy_plugins_and_the_executors_pass_the_conformance_checks() -> None:
    from invphys.plugins.executors import EXECUTORS
    from invphys.testing import check_feature_extractor, check_plugin_class, check_simulator

    for cls in (ToyOscillator, ToyFeatures, *EXECUTORS):
        check_plugin_class(cls)
    results = check_simulator(ToyOscillator(), n_runs=6)
    check_feature_extractor(ToyFeatures(), results)
