"""PPO settings and helpers shared by the ``ppo`` and ``gc_ppo`` optimisers (imports SB3 lazily)."""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field, field_validator

from invphys.core.interfaces import PluginConfig


class PPOSettings(PluginConfig):
    """The paper's PPO settings (sec. 3.4): every PPO variant uses them unless configured otherwise."""

    learning_rate: float = Field(3e-4, gt=0, description="Adam learning rate")
    ent_coef: float = Field(0.01, ge=0, description="entropy bonus coefficient")
    clip_range: float = Field(0.2, gt=0, description="PPO clip range")
    gamma: float = Field(0.99, gt=0, le=1, description="discount factor")
    gae_lambda: float = Field(0.95, ge=0, le=1, description="GAE lambda")
    n_steps: int = Field(256, ge=1, description="steps per env per update")
    batch_size: int = Field(64, ge=2, description="minibatch size")
    n_epochs: int = Field(10, ge=1, description="SGD epochs per update")
    net_arch: list[int] = Field(default_factory=lambda: [256, 256],
                                description="hidden layer widths of the policy and value MLPs")
    n_envs: int = Field(8, ge=1, description="parallel environments (one batched surrogate call per step)")
    horizon: int = Field(8, ge=1, description="episode length T (evaluations per rollout)")
    step_scale: float = Field(0.5, gt=0, description="s_{t+1} = clip(s_t + step_scale * a_t)")
    seed: int | None = Field(None, description="random seed (default: the problem's / run's seed)")
    torch_threads: int | None = Field(1, ge=1, le=1024, description="torch CPU threads while training (None: leave)")
    device: str = Field("cpu", description="torch device of the policy")

    @field_validator("net_arch")
    @classmethod
    def _widths(cls, v: list[int]) -> list[int]:
        if not v or any(w < 1 for w in v):
            raise ValueError("net_arch needs at least one layer of width >= 1")
        return v


def make_ppo(env: Any, cfg: PPOSettings, seed: int, tracker: Any = None) -> Any:
    """A stable-baselines3 PPO over ``env`` with ``cfg``'s settings; its logs go to ``tracker``."""
    from stable_baselines3 import PPO

    if cfg.torch_threads is not None:
        import torch

        torch.set_num_threads(cfg.torch_threads)
    arch = list(cfg.net_arch)
    model = PPO("MlpPolicy", env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps,
               batch_size=min(cfg.batch_size, cfg.n_steps * cfg.n_envs), n_epochs=cfg.n_epochs,
               gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_range=cfg.clip_range, ent_coef=cfg.ent_coef,
               policy_kwargs={"net_arch": {"pi": arch, "vf": arch}}, seed=seed, device=cfg.device, verbose=0)
    from invphys.tracking.sb3 import attach

    attach(model, tracker)  # also without a tracker: SB3's default logger writes a temp folder
    return model


def policy_actions(model: Any, obs: np.ndarray, stochastic_from: int) -> np.ndarray:
    """Deterministic actions for rows < ``stochastic_from``, sampled actions for the rest."""
    det, _ = model.predict(obs, deterministic=True)
    det = np.asarray(det, dtype=np.float64).reshape(len(obs), -1)
    if stochastic_from < len(obs):
        sto, _ = model.predict(obs[stochastic_from:], deterministic=False)
        det[stochastic_from:] = np.asarray(sto, dtype=np.float64).reshape(len(obs) - stochastic_from, -1)
    return det


def run_rollouts(model: Any, batch: Any, n_deterministic: int = 1) -> None:
    """Roll the policy for the task's horizon on an already-reset :class:`EpisodeBatch`."""
    for _ in range(batch.task.horizon):
        batch.step(policy_actions(model, batch.observe(), n_deterministic))
