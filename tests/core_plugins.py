"""Small plugin classes used by the foundation tests (registry, specs, CLI)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from invphys.core.interfaces import Optimizer, PluginConfig, Problem, Simulator
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.results import OptimizationResult, RunStats, SimulationResult, Trajectory


class RandomSearch(Optimizer):
    """Uniform random search over the problem's space (a baseline)."""

    name = "test_random_search"

    class Config(PluginConfig):
        sigma0: float = Field(0.3, gt=0)
        budget: int = Field(100, gt=0)

    def optimize(self, problem: Problem) -> OptimizationResult:
        rng = np.random.default_rng(problem.seed)
        points = problem.space.sample(min(problem.budget, self.config.budget), rng)
        scores = problem.evaluate(points)
        best = int(np.argmax(scores))
        return OptimizationResult(theta=problem.space.to_theta(points[best:best + 1])[0], point=points[best],
                                  score=float(scores[best]), evaluations=len(points))


class OtherRandomSearch(RandomSearch):
    """Same name as :class:`RandomSearch`, a different class (for the duplicate check)."""


class LineSimulator(Simulator):
    """A cheap analytic simulator: particles moving along a line at a parameter-dependent speed."""

    name = "test_line"
    version = "1"

    class Config(PluginConfig):
        frames: int = Field(5, gt=1)

    def parameter_space(self) -> ParameterSpace:
        return ParameterSpace((Parameter("speed", 0.1, 10.0, log=True), Parameter("offset", -1.0, 1.0)))

    def simulate(self, params, on_result=None):
        params = self.parameter_space().check(np.atleast_2d(params))
        results = []
        for i, (speed, offset) in enumerate(params):
            t = np.arange(self.config.frames, dtype=np.float64)
            pos = np.zeros((len(t), 1, 3), dtype=np.float32)
            pos[:, 0, 0] = offset + speed * t
            traj = Trajectory(positions=pos, damage=np.zeros((len(t), 1), np.float32),
                              labels=np.zeros(1, np.int8), frame_indices=t.astype(int), fps=1.0)
            res = SimulationResult(params=params[i], ok=True, trajectory=traj,
                                   stats=RunStats(substeps=len(t), backend="numpy", simulator=self.name))
            if on_result:
                on_result(i, res)
            results.append(res)
        return results
