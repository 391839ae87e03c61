"""The ``toy_spring`` simulator: a mass released from a stretched, damped spring (NumPy)."""

import time
from typing import Literal

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig, Simulator
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.results import RunStats, SimulationResult, Trajectory

#: (seconds simulated, frames per second) of each preset; every frame takes ``substeps`` steps
PRESETS = {"tiny": (1.0, 40), "standard": (3.0, 200)}


class SpringSimulator(Simulator):
    """A mass m on a spring (stiffness k, damping c) released from x0 = 5 cm.

    Integrates m x'' = -k x - c x' with semi-implicit Euler, all runs of a batch at once, and records
    the displacement x(t), the force on the wall F(t) = k x + c x' and the energy E(t) = k x^2 / 2 +
    m x'^2 / 2 at every step. A step too long for the stiffness (omega dt > 2) blows up; such runs are
    returned as failed.
    """

    name = "toy_spring"
    version = "1"  # bump when the same parameters and config give different results

    class Config(PluginConfig):
        """Settings of the toy spring."""

        preset: Literal["tiny", "standard"] = Field("tiny", description="duration and frame rate")
        backend: Literal["numpy"] = Field("numpy", description="compute backend (only NumPy)")
        substeps: int = Field(10, ge=1, le=1000, description="integration steps per frame")

    def parameter_space(self) -> ParameterSpace:
        return ParameterSpace((
            Parameter("k", 10.0, 1000.0, log=True, unit="N/m", description="spring stiffness"),
            Parameter("c", 0.01, 0.5, log=True, unit="N s/m", description="damping coefficient"),
            Parameter("m", 0.1, 2.0, unit="kg", description="mass"),
        ))

    def default_feature_extractor(self) -> str:
        return "toy_spring_features"

    def simulate(self, params, on_result=None):
        p = np.atleast_2d(self.parameter_space().check(params))  # raises on out-of-range input
        start = time.perf_counter()
        k, c, m = p[:, 0], p[:, 1], p[:, 2]
        duration, fps = PRESETS[self.config.preset]
        steps = int(duration * fps) * self.config.substeps
        dt = duration / steps
        x, v = np.full(len(p), 0.05), np.zeros(len(p))
        xs, forces, energy = (np.empty((steps + 1, len(p))) for _ in range(3))
        xs[0], forces[0], energy[0] = x, k * x, 0.5 * k * x * x
        with np.errstate(over="ignore", invalid="ignore"):
            for n in range(1, steps + 1):
                v = v + dt * (-k * x - c * v) / m
                x = x + dt * v
                xs[n], forces[n], energy[n] = x, k * x + c * v, 0.5 * (k * x * x + m * v * v)
        blown = ~np.isfinite(xs).all(axis=0) | (np.abs(xs) > 1.0).any(axis=0)
        times = np.arange(steps + 1) * dt
        wall = (time.perf_counter() - start) / len(p)
        results = []
        for i in range(len(p)):
            stats = RunStats(substeps=steps, wall_time_s=wall, backend=self.config.backend, device="cpu",
                             preset=self.config.preset, simulator=self.name, simulator_version=self.version)
            if blown[i]:
                res = SimulationResult(params=p[i], ok=False, stats=stats,
                                       failure="blow-up: |x| > 1 m (omega dt > 2: raise substeps)")
            else:
                traj = Trajectory()
                traj.add_series("displacement", times, xs[:, i], unit="m", description="mass position")
                traj.add_series("force", times, forces[:, i], unit="N", description="force on the wall")
                traj.add_series("energy", times, energy[:, i], unit="J", description="mechanical energy")
                res = SimulationResult(params=p[i], ok=True, stats=stats, trajectory=traj)
            if on_result is not None:
                on_result(i, res)
            results.append(res)
        return results

    def render(self, trajectory, path, *, max_frames=60, animation="gif", **options):
        """The mass on its spring at most ``max_frames`` times, an animation and a plot of the series."""
        if options:
            raise InvphysError(f"toy_spring's renderer takes no options (got {', '.join(options)})")
        from invphys_toy_spring.render import render_spring

        return render_spring(trajectory, path, max_frames=max_frames, animation=animation)
