"""Gymnasium environments for inverse design with a surrogate (paper sec. 3.4 and 4.1).

* :class:`~invphys.envs.task.InverseTask`: the NumPy logic shared by both environments (state update
  ``s_{t+1} = clip(s_t + step_scale * a_t)``, observation, sparse best-score reward at step T);
* :class:`~invphys.envs.single.InverseDesignEnv`: one episode at a time, a ``gymnasium.Env``;
* :class:`~invphys.envs.vec.InverseVecEnv`: ``n_envs`` episodes as a stable-baselines3 ``VecEnv``
  whose step makes ONE batched surrogate call for all its envs.

Import the submodules directly (they import gymnasium / stable-baselines3).
"""

from __future__ import annotations

__all__ = ["InverseDesignEnv", "InverseTask", "InverseVecEnv"]


def __getattr__(name: str):  # lazy: keep ``import invphys.envs`` cheap
    if name == "InverseTask":
        from invphys.envs.task import InverseTask

        return InverseTask
    if name == "InverseDesignEnv":
        from invphys.envs.single import InverseDesignEnv

        return InverseDesignEnv
    if name == "InverseVecEnv":
        from invphys.envs.vec import InverseVecEnv

        return InverseVecEnv
    raise AttributeError(name)
