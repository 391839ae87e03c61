"""A stable-baselines3 ``VecEnv`` running many inverse-design episodes with one surrogate call per step."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from invphys.envs.task import EpisodeBatch, InverseTask


class InverseVecEnv(VecEnv):
    """``n_envs`` episodes of an :class:`InverseTask` stepped together.

    ``step`` evaluates the new states of all envs in ONE ``task.predict`` call (the point of the class:
    the surrogate is batched). Finished episodes auto-reset, with the final observation in
    ``infos[i]["terminal_observation"]`` and the episode's return, length and time in
    ``infos[i]["episode"]`` (as SB3's ``VecMonitor`` writes them: SB3 logs ``rollout/ep_rew_mean``
    from them); restarting costs no evaluation (the start point's features are cached).
    """

    def __init__(self, task: InverseTask, n_envs: int = 8, seed: int = 0) -> None:
        low, high = task.obs_bounds()
        obs_space = gym.spaces.Box(low=low, high=high, dtype=np.float32)
        act_space = gym.spaces.Box(-1.0, 1.0, shape=(task.dim,), dtype=np.float32)
        self.render_mode = None
        super().__init__(n_envs, obs_space, act_space)
        self.task = task
        self._rng = np.random.default_rng(seed)
        self._batch = EpisodeBatch(task, n_envs, self._rng)
        self._actions: np.ndarray | None = None
        self.predict_calls = 0
        self._started = np.full(n_envs, time.perf_counter())

    def reset(self) -> np.ndarray:
        if self._seeds[0] is not None:
            self._rng = np.random.default_rng(self._seeds[0])
            self._batch.rng = self._rng
        self._reset_seeds()
        self._batch.reset()
        self._started[:] = time.perf_counter()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return self._batch.observe()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        assert self._actions is not None, "step_async first"
        rewards, done = self._batch.step(self._actions)
        self.predict_calls += 1
        obs = self._batch.observe()
        infos: list[dict[str, Any]] = [{"score": float(r)} for r in self._batch.r]
        rows = np.flatnonzero(done)
        for i in rows:
            infos[i]["terminal_observation"] = obs[i].copy()
            infos[i]["best"] = float(self._batch.best[i])
            infos[i]["episode"] = {"r": float(rewards[i]), "l": int(self.task.horizon),
                                   "t": round(time.perf_counter() - self._started[i], 6)}
            self._started[i] = time.perf_counter()
        if len(rows):
            self._batch.reset(rows)
            obs = self._batch.observe()
        self._actions = None
        return obs, rewards, done.copy(), infos

    def close(self) -> None:
        pass

    # -- VecEnv plumbing: the envs are rows of one batch, so attributes are shared ----------------
    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        if attr_name == "render_mode":
            return [None for _ in self._get_indices(indices)]
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        return [getattr(self, method_name)(*method_args, **method_kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]
