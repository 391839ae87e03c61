"""Gymnasium environments for inverse design with a surrogate (paper sec. 3.4 and 4.1).

* :class:`~invphys.envs.task.InverseTask`: the NumPy logic shared by both environments (state update
  ``s_{t+1} = clip(s_t + step_scale * a_t)``, observation, sparse best-score reward at step T);
* :class:`~invphys.envs.single.InverseDesignEnv`: one episode at a time, a ``gymnasium.Env``;
* :class:`~invphys.envs.vec.InverseVecEnv`: ``n_envs`` episodes as a stable-baselines3 ``VecEnv``
  whose step makes ONE batched surrogate call for all its envs.

* the Gymnasium id ``invphys/Inversion-v0`` (:func:`invphys.inversion_env.make_inversion_env`, which lives
  above the inverter because it also takes a bundle), registered when this package is imported
  (``import invphys.envs``; ``gym.make`` then finds it and imports its entry point).

Import the submodules directly (they import gymnasium / stable-baselines3).
"""

from __future__ import annotations

__all__ = ["ENV_IDS", "InverseDesignEnv", "InverseTask", "InverseVecEnv", "register_envs"]

#: Gymnasium ids this package registers, and their entry points
ENV_IDS: dict[str, str] = {"invphys/Inversion-v0": "invphys.inversion_env:make_inversion_env"}


def register_envs() -> list[str]:
    """Register :data:`ENV_IDS` with Gymnasium (idempotent); returns the ids now registered."""
    try:
        import gymnasium
    except ImportError:  # the rl extra is not installed: nothing to register
        return []
    for env_id, entry_point in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point, disable_env_checker=False)
    return list(ENV_IDS)


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


register_envs()
