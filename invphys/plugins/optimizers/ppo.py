"""Per-objective PPO (paper sec. 4.1): a policy trained for one objective, refining a point over T steps."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import Problem
from invphys.core.results import OptimizationResult
from invphys.core.standardiser import Standardiser
from invphys.plugins.optimizers._base import BuiltinOptimizer, Tracker
from invphys.plugins.optimizers._rl import PPOSettings, make_ppo, run_rollouts


class PPOOptimizer(BuiltinOptimizer):
    """PPO trained on one problem's objective; returns the best point seen while training.

    Observation ``[s, y_hat, R(y_hat), t/T]`` (``y_hat`` standardised with the problem's
    ``feature_mean``/``feature_std`` info, else with statistics of ``stat_samples`` random points,
    which count as evaluations); ``s_{t+1} = clip(s_t + step_scale * a_t)`` from the box centre (or
    ``problem.initial``); sparse reward = best R among the T states at step T. Every environment step
    is one surrogate evaluation, so training spends ``total_timesteps`` (rounded down to whole updates
    of ``n_steps * n_envs``) and the budget is ``1 + total_timesteps + T`` (start point, training,
    a final deterministic rollout). A smaller ``problem.budget`` shrinks training to fit.
    ``problem.info["tracker"]``, when set, receives stable-baselines3's logs once per rollout.
    """

    name: ClassVar[str] = "ppo"
    #: per-objective: the invert stage trains one policy per named objective (per target only when the
    #: spec has no objectives)
    problems: ClassVar[str] = "objectives"

    class Config(PPOSettings):
        total_timesteps: int = Field(49_152, ge=1, description="environment steps (= evaluations) to train")
        stat_samples: int = Field(64, ge=2, description="random points for feature statistics if needed")

    @property
    def evaluation_budget(self) -> int:
        cfg = self.config
        rollout = cfg.n_steps * cfg.n_envs
        return 1 + max(cfg.total_timesteps // rollout, 1) * rollout + cfg.horizon

    def optimize(self, problem: Problem) -> OptimizationResult:
        from invphys.envs.task import EpisodeBatch, InverseTask
        from invphys.envs.vec import InverseVecEnv

        cfg = self.config
        space = problem.space
        seed = int(problem.seed if cfg.seed is None else cfg.seed)
        rng = np.random.default_rng(seed)
        tracker = Tracker(problem)
        mean = problem.info.get("feature_mean")
        std = problem.info.get("feature_std")
        if mean is None or std is None:
            if tracker.remaining < cfg.stat_samples:
                raise InvphysError(f"ppo: budget {tracker.budget} is too small for {cfg.stat_samples} "
                                   f"feature-statistics samples")
            pts = space.sample(cfg.stat_samples, rng)
            y = np.asarray(problem.predict(space.clip(pts)), dtype=np.float64)
            tracker.record(pts, y, np.asarray(problem.objective(y), dtype=np.float64).reshape(-1))
            mean, std = Standardiser.fit(y)
        start = (np.full(space.dim, 0.5 * (space.low + space.high)) if problem.initial is None
                 else np.asarray(problem.initial, dtype=np.float64).reshape(space.dim))
        y0 = np.asarray(problem.predict(space.clip(start[None, :])), dtype=np.float64)
        tracker.record(start[None, :], y0, np.asarray(problem.objective(y0), dtype=np.float64).reshape(-1))

        def score(y: np.ndarray, goals: np.ndarray | None) -> np.ndarray:
            return np.asarray(problem.objective(y), dtype=np.float64).reshape(-1)

        task = InverseTask(low=space.low, high=space.high, dim=space.dim, predict=problem.predict, score=score,
                           feature_mean=mean, feature_std=std, horizon=cfg.horizon, step_scale=cfg.step_scale,
                           start=start, start_features=y0[0], on_evaluate=tracker.record)
        rollout = cfg.n_steps * cfg.n_envs
        updates = min(cfg.total_timesteps // rollout, (tracker.remaining - cfg.horizon) // rollout)
        if updates < 1:
            raise InvphysError(
                f"ppo: one update needs n_steps * n_envs = {rollout} evaluations plus T = {cfg.horizon}; "
                f"the budget leaves {tracker.remaining} (raise total_timesteps/budget or lower n_steps/n_envs)")
        env = InverseVecEnv(task, cfg.n_envs, seed)
        model = make_ppo(env, cfg, seed, problem.info.get("tracker"))
        model.learn(total_timesteps=updates * rollout)
        batch = EpisodeBatch(task, 1, rng)
        batch.reset()
        run_rollouts(model, batch)
        return tracker.result(timesteps=updates * rollout, updates=updates)
