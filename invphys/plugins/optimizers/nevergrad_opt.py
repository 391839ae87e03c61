"""Any nevergrad optimiser by name (``optimizer: NGOpt``, ``TwoPointsDE``, ``PSO``, ...)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError, did_you_mean
from invphys.core.interfaces import PluginConfig, Problem
from invphys.core.results import OptimizationResult
from invphys.plugins.optimizers._base import BudgetExhausted, BuiltinOptimizer, Tracker


class NevergradOptimizer(BuiltinOptimizer):
    """A nevergrad optimiser over the space's box, asked ``batch_size`` points at a time.

    ``optimizer`` is any name in ``nevergrad.optimizers.registry`` (unknown names are answered with a
    did-you-mean). Points are evaluated in batches of ``batch_size`` (nevergrad's ``num_workers``) in
    one surrogate call; the total never exceeds ``min(budget, problem.budget)``.
    """

    name: ClassVar[str] = "nevergrad"

    class Config(PluginConfig):
        optimizer: str = Field("NGOpt", min_length=1, description="nevergrad optimiser name")
        budget: int = Field(5000, ge=1, description="surrogate evaluations per optimisation")
        batch_size: int = Field(20, ge=1, description="points asked (and evaluated together) per round")
        seed: int | None = Field(None, description="random seed (default: the problem's seed)")

    def optimize(self, problem: Problem) -> OptimizationResult:
        import nevergrad as ng

        cfg = self.config
        registry = ng.optimizers.registry
        if cfg.optimizer not in registry:
            raise InvphysError(f"unknown nevergrad optimizer {cfg.optimizer!r}."
                               f"{did_you_mean(cfg.optimizer, list(registry))} "
                               f"(e.g. NGOpt, CMA, TwoPointsDE, PSO, OnePlusOne)")
        space = problem.space
        tracker = Tracker(problem, cfg.budget)
        param = ng.p.Array(shape=(space.dim,), lower=space.low, upper=space.high)
        if problem.initial is not None:
            param.value = np.clip(np.asarray(problem.initial, dtype=np.float64).reshape(-1),
                                  space.low, space.high)
        seed = int(problem.seed if cfg.seed is None else cfg.seed)
        param.random_state = np.random.RandomState(seed % (2**32))
        opt = registry[cfg.optimizer](parametrization=param, budget=tracker.budget,
                                      num_workers=cfg.batch_size)
        try:
            while tracker.remaining > 0:
                n = min(cfg.batch_size, tracker.remaining)
                cands = [opt.ask() for _ in range(n)]
                scores = tracker.evaluate(np.stack([np.asarray(c.value, dtype=np.float64) for c in cands]))
                for c, s in zip(cands, scores, strict=True):
                    opt.tell(c, float(-s) if np.isfinite(s) else 1e12)
        except BudgetExhausted:
            pass
        return tracker.result(optimizer=cfg.optimizer)
