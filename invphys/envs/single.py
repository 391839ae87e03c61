"""A single-episode Gymnasium environment over an :class:`~invphys.envs.task.InverseTask`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from invphys.envs.task import EpisodeBatch, InverseTask


class InverseDesignEnv(gym.Env):
    """Refine a search point over T steps to maximise a score of its predicted features.

    Action: ``a`` in [-1, 1]^dim, ``s_{t+1} = clip(s_t + step_scale * a)``. Observation and reward
    as in :class:`InverseTask`. ``reset(options={"goal": y_star})`` fixes a goal-conditioned
    episode's target (in feature units) instead of sampling one.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, task: InverseTask, describe: Callable[[np.ndarray], dict[str, Any]] | None = None) -> None:
        super().__init__()
        self.task = task
        self.describe = describe
        low, high = task.obs_bounds()
        self.observation_space = gym.spaces.Box(low=low, high=high, dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(task.dim,), dtype=np.float32)
        self._batch: EpisodeBatch | None = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self._batch = EpisodeBatch(self.task, 1, self.np_random)
        goal = (options or {}).get("goal")
        self._batch.reset(goals=None if goal is None else np.asarray(goal, dtype=np.float64)[None, :])
        return self._batch.observe()[0], self._info()

    def step(self, action: np.ndarray):
        if self._batch is None:
            raise RuntimeError("call reset() before step()")
        rewards, done = self._batch.step(np.asarray(action)[None, :])
        obs = self._batch.observe()[0]
        return obs, float(rewards[0]), bool(done[0]), False, self._info()

    def _info(self) -> dict[str, Any]:
        """R (this state's recovery reward), R_best (the best so far; before any step, R) and, with a
        ``describe`` function, the state's parameters: ``theta``, ``params`` by name, ``units``."""
        assert self._batch is not None
        r, best = float(self._batch.r[0]), float(self._batch.best[0])
        best = best if np.isfinite(best) else r
        info: dict[str, Any] = {"R": r, "R_best": best, "score": r, "best": best}
        if self.describe is not None:
            info.update(self.describe(self._batch.s[0]))
        return info
