"""CMA-ES (the ``cma`` package) over a search space's box (paper sec. 4.1: popsize 20, sigma0 0.3)."""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig, Problem
from invphys.core.results import OptimizationResult
from invphys.plugins.optimizers._base import BudgetExhausted, BuiltinOptimizer, Tracker


class CMAES(BuiltinOptimizer):
    """Covariance Matrix Adaptation Evolution Strategy with box bounds.

    CMA-ES runs in the unit cube mapped affinely onto the space's box, so ``sigma0`` is relative to
    the box width in every space (0.3 in [0, 1]^9 is the paper's setting; in the latent box
    [-3, 3]^4 it is 0.3 * 6). It starts at ``problem.initial`` when the problem has one, else at the
    box centre (``x0: center``) or a seeded random point (``x0: random``). It never evaluates more than
    ``min(budget, problem.budget)`` points; the last generation is truncated to the remaining budget.
    When cma stops on its own criteria before the budget is spent (converged, or a flat objective), it
    restarts from a seeded random point with the same ``sigma0`` (``restarts: true``), so the whole
    budget is used; the result is the best point over all restarts.
    """

    name: ClassVar[str] = "cma_es"

    class Config(PluginConfig):
        popsize: int = Field(20, ge=2, description="population size per generation")
        sigma0: float = Field(0.3, gt=0, description="initial step size, relative to the box width")
        budget: int = Field(5000, ge=1, description="surrogate evaluations per optimisation")
        x0: Literal["center", "random"] = Field("center", description="start when the problem has none")
        seed: int | None = Field(None, description="random seed (default: the problem's seed)")
        tolfun: float = Field(1e-11, ge=0, description="cma's tolfun stopping tolerance")
        restarts: bool = Field(True, description="restart from a random point when cma stops before the budget")

    def optimize(self, problem: Problem) -> OptimizationResult:
        import cma

        cfg = self.config
        space = problem.space
        tracker = Tracker(problem, cfg.budget)
        width = space.high - space.low
        seed = int(problem.seed if cfg.seed is None else cfg.seed)
        rng = np.random.default_rng(seed)
        if problem.initial is not None:
            x0 = (np.asarray(problem.initial, dtype=np.float64).reshape(-1) - space.low) / width
            if x0.shape != (space.dim,):
                raise InvphysError(f"initial point has {x0.size} coordinates, the space {space.name!r} "
                                   f"has {space.dim}")
        elif cfg.x0 == "random":
            x0 = rng.uniform(0.0, 1.0, space.dim)
        else:
            x0 = np.full(space.dim, 0.5)
        x0 = np.clip(x0, 0.0, 1.0)
        restarts = -1
        stop: dict = {}
        try:
            while tracker.remaining > 0:
                restarts += 1
                start = x0 if restarts == 0 else rng.uniform(0.0, 1.0, space.dim)
                opts = {"popsize": cfg.popsize, "bounds": [0.0, 1.0], "seed": (seed + restarts) % (2**31 - 2) + 1,
                        "verbose": -9, "tolfun": cfg.tolfun, "maxfevals": tracker.remaining}
                es = cma.CMAEvolutionStrategy(start.tolist(), cfg.sigma0, opts)
                stop = {}
                while tracker.remaining > 0:
                    stop = dict(es.stop())
                    if stop:
                        break
                    unit = np.clip(np.asarray(es.ask(), dtype=np.float64), 0.0, 1.0)
                    n = min(len(unit), tracker.remaining)
                    scores = tracker.evaluate(space.low + unit[:n] * width)
                    if n < len(unit):
                        break  # truncated last generation: cma needs full populations
                    es.tell(list(unit), list(-scores))
                if not cfg.restarts:
                    break
        except BudgetExhausted:
            pass
        if not stop:
            stop = {"budget": tracker.budget}
        return tracker.result(stop={k: str(v) for k, v in stop.items()}, x0=(space.low + x0 * width).tolist(),
                              sigma0=cfg.sigma0, restarts=restarts)
