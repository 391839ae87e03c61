"""Warm start (paper sec. 3.5): a goal-conditioned policy's proposal starts a tight CMA-ES in [0, 1]^d."""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig, Problem
from invphys.core.results import OptimizationResult
from invphys.plugins.optimizers._base import BuiltinOptimizer


class WarmStart(BuiltinOptimizer):
    """GC-PPO proposal, decoded to normalised parameters, refined by CMA-ES in the raw space.

    ``optimize(problem)`` takes a problem in the *policy's* space (raw or latent) and:

    1. rolls the policy ``rollouts`` times (first deterministic, rest sampled): ``rollouts * T``
       evaluations (paper: 5 x 8 = 40);
    2. decodes the best proposal to theta0 in [0, 1]^d and runs CMA-ES there (``sigma0`` 0.1,
       ``popsize`` 20, ``budget`` 500 evaluations) on the shared surrogate over theta
       (``problem.info["theta_predict"]``); CMA-ES always works in [0, 1]^d, as in the paper;
    3. returns the better of theta0 and the CMA-ES optimum, so it is never worse than its start.

    The count reported is policy rollouts + CMA-ES evaluations (40 + 500 = 540 with the defaults),
    plus one evaluation of theta0 on the shared surrogate when the policy's problem used another
    evaluator (``own_head``). The policy is a trained ``gc_ppo``: set by :meth:`attach` (the invert
    stage does so for ``policy: <label>``) or loaded from ``policy_path``.
    """

    name: ClassVar[str] = "warm_start"
    problems: ClassVar[str] = "targets"

    class Config(PluginConfig):
        policy: str | None = Field(None, description="label of the gc_ppo entry whose policy starts CMA-ES")
        policy_path: str | None = Field(None, description="directory of a saved gc_ppo policy")
        rollouts: int = Field(5, ge=1, description="policy rollouts (x T evaluations) before CMA-ES")
        sigma0: float = Field(0.1, gt=0, description="CMA-ES initial step size in [0, 1]^d")
        popsize: int = Field(20, ge=2, description="CMA-ES population size")
        budget: int = Field(500, ge=1, description="CMA-ES evaluations")
        seed: int | None = Field(None, description="random seed (default: the problem's seed)")

    def __init__(self, config: Any = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self.policy: Any = None

    def attach(self, policy: Any) -> WarmStart:
        """Use ``policy`` (a prepared goal-conditioned optimiser) for the proposals."""
        if not getattr(policy, "goal_conditioned", False) or not hasattr(policy, "propose"):
            raise InvphysError(f"warm_start needs a gc_ppo-like policy (goal-conditioned, with propose()), "
                               f"got {type(policy).__name__}")
        self.policy = policy
        return self

    def _policy(self) -> Any:
        if self.policy is None and self.config.policy_path:
            from invphys.plugins.optimizers.gc_ppo import GoalConditionedPPO

            self.policy = GoalConditionedPPO.load(self.config.policy_path)
        if self.policy is None:
            raise InvphysError("warm_start has no policy: name a gc_ppo entry with `policy: <label>` "
                               "or a saved one with `policy_path`")
        return self.policy

    @property
    def evaluation_budget(self) -> int:
        horizon = self.policy.config.horizon if self.policy is not None else 8
        return self.config.rollouts * horizon + self.config.budget

    def optimize(self, problem: Problem) -> OptimizationResult:
        from invphys.core.spaces import build_problem, raw_space
        from invphys.plugins.optimizers.cma_es import CMAES

        t0 = time.perf_counter()
        cfg = self.config
        policy = self._policy()
        horizon = policy.config.horizon
        rollouts = min(cfg.rollouts, max(problem.budget // horizon, 1))
        sub = Problem(space=problem.space, predict=problem.predict, objective=problem.objective,
                      budget=rollouts * horizon, target=problem.target, seed=problem.seed, info=problem.info)
        proposal = policy.propose(sub, rollouts)
        theta0 = np.asarray(proposal.theta, dtype=np.float64)
        theta_predict = problem.info.get("theta_predict")
        if theta_predict is None:
            if problem.space.name != "raw" and problem.space.dim != theta0.size:
                raise InvphysError("warm_start needs problem.info['theta_predict'] (the shared surrogate "
                                   "over normalised parameters); build the problem with build_problem()")
            theta_predict = problem.predict
        spent = proposal.evaluations
        start_score = proposal.score
        if problem.info.get("evaluator", "shared") != "shared":
            y0 = np.asarray(theta_predict(theta0[None, :]), dtype=np.float64)
            start_score = float(np.asarray(problem.objective(y0)).reshape(-1)[0])
            spent += 1
        cma_budget = min(cfg.budget, problem.budget - spent)
        if cma_budget < 1:
            raise InvphysError(f"warm_start: budget {problem.budget} leaves nothing for CMA-ES after "
                               f"{spent} policy evaluations")
        raw = build_problem(raw_space(theta0.size), problem.objective, cma_budget, predict=theta_predict,
                            target=problem.target, initial=theta0,
                            seed=int(problem.seed if cfg.seed is None else cfg.seed))
        refined = CMAES(popsize=cfg.popsize, sigma0=cfg.sigma0, budget=cma_budget).optimize(raw)
        history = list(proposal.history) + [(spent + e, max(s, start_score)) for e, s in refined.history]
        improved = refined.score > start_score
        theta = refined.theta if improved else theta0
        score = refined.score if improved else start_score
        return OptimizationResult(
            theta=theta, point=theta, score=float(score), evaluations=spent + refined.evaluations,
            history=history, wall_time_s=time.perf_counter() - t0,
            info={"start_theta": theta0.tolist(), "start_score": float(start_score),
                  "policy_evaluations": spent, "cma_evaluations": refined.evaluations,
                  "improved": bool(improved), "predicted": refined.info.get("predicted") if improved
                  else proposal.info.get("predicted")})
