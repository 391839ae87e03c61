"""CMA-ES (the ``cma`` package) over a search space's box (paper sec. 4.1: popsize 20, sigma0 0.3)."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig, Problem, SearchSpace
from invphys.core.results import OptimizationResult
from invphys.plugins.optimizers._base import AskTell, BudgetExhausted, BuiltinOptimizer, Tracker


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

    def ask_tell(self, space: SearchSpace, seed: int = 0, initial: np.ndarray | None = None,
                 budget: int | None = None) -> CMAAskTell:
        """An ask/tell CMA-ES over ``space`` with this configuration (``budget``: evaluations it may
        be told in all; default ``config.budget``). Start: ``initial``, else per ``x0``."""
        cfg = self.config
        width = space.high - space.low
        rng = np.random.default_rng(int(seed))
        if initial is not None:
            x0 = (np.asarray(initial, dtype=np.float64).reshape(-1) - space.low) / width
            if x0.shape != (space.dim,):
                raise InvphysError(f"initial point has {x0.size} coordinates, the space {space.name!r} "
                                   f"has {space.dim}")
        elif cfg.x0 == "random":
            x0 = rng.uniform(0.0, 1.0, space.dim)
        else:
            x0 = np.full(space.dim, 0.5)
        return CMAAskTell(space, np.clip(x0, 0.0, 1.0), cfg.sigma0, cfg.popsize, int(seed), rng,
                          int(cfg.budget if budget is None else budget), cfg.tolfun, cfg.restarts)

    def optimize(self, problem: Problem) -> OptimizationResult:
        cfg = self.config
        tracker = Tracker(problem, cfg.budget)
        seed = int(problem.seed if cfg.seed is None else cfg.seed)
        search = self.ask_tell(problem.space, seed, problem.initial, tracker.budget)
        try:
            while tracker.remaining > 0:
                points = search.ask()
                if len(points) == 0:
                    break
                n = min(len(points), tracker.remaining)
                scores = tracker.evaluate(points[:n])
                search.tell(points[:n], scores)
                if n < len(points):
                    break
        except BudgetExhausted:
            pass
        stop = search.stop or {"budget": tracker.budget}
        return tracker.result(stop={k: str(v) for k, v in stop.items()}, x0=search.x0_point.tolist(),
                              sigma0=cfg.sigma0, restarts=search.restarts)


class CMAAskTell(AskTell):
    """CMA-ES (the ``cma`` package) behind :class:`AskTell`, in the unit cube mapped onto the box.

    A generation told only in part (a truncated last batch) is not passed to cma (it needs full
    populations). When cma stops on its own criteria before ``budget`` points were told, it restarts
    from a seeded random point (``restarts``), else :attr:`done` becomes True.
    """

    def __init__(self, space: SearchSpace, x0: np.ndarray, sigma0: float, popsize: int, seed: int,
                 rng: np.random.Generator, budget: int, tolfun: float, restarts: bool) -> None:
        super().__init__()
        self.space, self.x0, self.sigma0, self.popsize = space, x0, sigma0, popsize
        self.seed, self.rng, self.budget, self.tolfun, self.allow_restarts = seed, rng, budget, tolfun, restarts
        self.width = space.high - space.low
        self.restarts = -1
        self.stop: dict = {}
        self._finished = False
        self._pending: np.ndarray | None = None
        self._es = self._new_es()

    @property
    def x0_point(self) -> np.ndarray:
        return self.space.low + self.x0 * self.width

    def _new_es(self) -> Any:
        import cma

        self.restarts += 1
        start = self.x0 if self.restarts == 0 else self.rng.uniform(0.0, 1.0, self.space.dim)
        opts = {"popsize": self.popsize, "bounds": [0.0, 1.0],
                "seed": (self.seed + self.restarts) % (2**31 - 2) + 1, "verbose": -9, "tolfun": self.tolfun,
                "maxfevals": max(self.budget - self.told, 1)}
        self.stop = {}
        return cma.CMAEvolutionStrategy(start.tolist(), self.sigma0, opts)

    @property
    def done(self) -> bool:
        return self._finished or self.told >= self.budget

    def _ask(self) -> np.ndarray:
        self.stop = dict(self._es.stop())
        if self.stop:
            if not self.allow_restarts:
                self._finished = True
                return np.empty((0, self.space.dim))
            self._es = self._new_es()
        unit = np.clip(np.asarray(self._es.ask(), dtype=np.float64), 0.0, 1.0)
        self._pending = unit
        return self.space.low + unit * self.width

    def _tell(self, points: np.ndarray, scores: np.ndarray) -> None:
        if self._pending is not None and len(points) == len(self._pending):
            self._es.tell(list(self._pending), list(-scores))
        self._pending = None
