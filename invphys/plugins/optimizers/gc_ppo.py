"""Goal-conditioned PPO (paper sec. 3.4): one policy, trained once, that inverts any target in T steps."""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import Problem, SearchSpace
from invphys.core.objectives import recovery_reward
from invphys.core.results import OptimizationResult
from invphys.core.standardiser import Standardiser
from invphys.models.base import (
    LegacyPickleError,
    check_state,
    first_line,
    read_json_mapping,
    read_weights_npz,
)
from invphys.plugins.optimizers._base import BuiltinOptimizer, Tracker
from invphys.plugins.optimizers._rl import PPOSettings, make_ppo, run_rollouts


class GoalConditionedPPO(BuiltinOptimizer):
    """A PPO policy conditioned on the target features y*.

    :meth:`prepare` trains it on targets drawn uniformly from ``train_targets`` (the training
    partition's features) plus N(0, ``target_noise``) noise in standardised feature space (z-scores
    with the training targets' mean and std). Observation ``[s, y_hat, y*, R_gt, t/T]`` (``y_hat``,
    ``y*`` standardised); every episode starts at the box centre; ``s_{t+1} = clip(s_t + step_scale *
    a_t)``; sparse reward = the best R_gt (eq. 1, with ``scales`` and ``kappa``) among the T states, at
    step T. :meth:`optimize` then rolls the policy for T steps towards ``problem.target``: ``rollouts``
    episodes in parallel (the first deterministic, the rest sampled), ``rollouts * T`` evaluations, and
    returns the best state. :meth:`save`/:meth:`load` persist the trained policy.
    """

    name: ClassVar[str] = "gc_ppo"
    goal_conditioned: ClassVar[bool] = True
    problems: ClassVar[str] = "targets"

    class Config(PPOSettings):
        total_timesteps: int = Field(500_000, ge=1, description="training environment steps")
        target_noise: float = Field(0.05, ge=0, description="std of goal noise in standardised feature space")
        kappa: float = Field(3.0, gt=0, description="sharpness of the recovery reward R_gt")
        rollouts: int = Field(1, ge=1, description="episodes per optimize call (first deterministic)")

    def __init__(self, config: Any = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self.model: Any = None
        self.meta: dict[str, Any] = {}
        self.metrics: dict[str, Any] = {}

    @property
    def evaluation_budget(self) -> int:
        return self.config.rollouts * self.config.horizon

    @property
    def prepared(self) -> bool:
        return self.model is not None

    # -- training ------------------------------------------------------------------------------
    def prepare(self, space: SearchSpace, predict: Callable[[np.ndarray], np.ndarray],
                train_targets: np.ndarray, scales: np.ndarray, progress: bool = False,
                tracker: Any = None, penalty: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, Any]:
        """Train the policy on ``train_targets`` (N, M) in ``space`` with the feature predictor ``predict``.

        ``penalty(features) -> (B,)`` is subtracted from R_gt in the reward and the observation (the
        uncertainty penalty: ``UncertaintyPenalty.penalty`` with ``predict`` from the same penalty).

        ``tracker`` receives stable-baselines3's logs once per rollout (``rollout/ep_rew_mean``,
        ``train/value_loss``, ...) at ``step = timesteps``, and the final ``train_recovery``.
        """
        from invphys.envs.task import EpisodeBatch, InverseTask
        from invphys.envs.vec import InverseVecEnv

        cfg = self.config
        targets = np.asarray(train_targets, dtype=np.float64)
        if targets.ndim != 2 or targets.shape[0] < 2:
            raise InvphysError(f"gc_ppo needs >= 2 training targets (N, M), got shape {targets.shape}")
        targets = targets[np.all(np.isfinite(targets), axis=1)]
        scales = np.asarray(scales, dtype=np.float64).reshape(-1)
        mean, std = Standardiser.fit(targets)
        seed = int(0 if cfg.seed is None else cfg.seed)
        kappa, noise = cfg.kappa, cfg.target_noise

        def sample_goals(rng: np.random.Generator, n: int) -> np.ndarray:
            z = (targets[rng.integers(0, len(targets), size=n)] - mean) / std
            return (z + rng.normal(0.0, noise, size=z.shape)) * std + mean

        def score(y: np.ndarray, goals: np.ndarray | None) -> np.ndarray:
            r = recovery_reward(y, goals, scales, kappa)
            return r if penalty is None else np.asarray(r, dtype=np.float64) - penalty(y)

        task = InverseTask(low=space.low, high=space.high, dim=space.dim, predict=predict, score=score,
                           feature_mean=mean, feature_std=std, horizon=cfg.horizon, step_scale=cfg.step_scale,
                           goal_sampler=sample_goals)
        env = InverseVecEnv(task, cfg.n_envs, seed)
        self.model = make_ppo(env, cfg, seed, tracker)
        t0 = time.perf_counter()
        self.model.learn(total_timesteps=cfg.total_timesteps, progress_bar=progress)
        train_s = time.perf_counter() - t0
        self.meta = {"space": {"name": space.name, "dim": space.dim, "low": space.low, "high": space.high},
                     "feature_mean": mean.tolist(), "feature_std": std.tolist(), "scales": scales.tolist(),
                     "start": task.start.tolist(), "start_features": task.start_features.tolist()}
        # recovery of the deterministic policy on (noise-free) training targets
        rng = np.random.default_rng(seed + 1)
        sample = targets[rng.choice(len(targets), size=min(64, len(targets)), replace=False)]
        eval_task = InverseTask(low=space.low, high=space.high, dim=space.dim, predict=predict, score=score,
                                feature_mean=mean, feature_std=std, horizon=cfg.horizon,
                                step_scale=cfg.step_scale, start=task.start, start_features=task.start_features,
                                goal_sampler=sample_goals)
        batch = EpisodeBatch(eval_task, len(sample), rng)
        batch.reset(goals=sample)
        run_rollouts(self.model, batch, n_deterministic=len(sample))
        steps = int(self.model.num_timesteps)
        self.metrics = {"timesteps": steps, "train_time_s": train_s, "steps_per_s": steps / max(train_s, 1e-9),
                        "surrogate_calls": env.predict_calls, "train_recovery": float(batch.best.mean())}
        if tracker is not None:
            tracker.log_scalar("train_recovery", self.metrics["train_recovery"], steps)
            tracker.flush()
        return dict(self.metrics)

    # -- inference -----------------------------------------------------------------------------
    def optimize(self, problem: Problem) -> OptimizationResult:
        return self.propose(problem, self.config.rollouts)

    def propose(self, problem: Problem, rollouts: int) -> OptimizationResult:
        """Best of ``rollouts`` policy episodes towards ``problem.target`` (the first deterministic)."""
        from invphys.envs.task import EpisodeBatch, InverseTask

        if self.model is None:
            raise InvphysError("gc_ppo has no trained policy: call prepare() (the invert stage does) or load()")
        if problem.target is None:
            raise InvphysError("gc_ppo inverts targets: the problem needs a target feature vector")
        cfg = self.config
        space, meta = problem.space, self.meta
        if space.dim != meta["space"]["dim"] or (space.low, space.high) != (meta["space"]["low"],
                                                                             meta["space"]["high"]):
            raise InvphysError(f"gc_ppo policy was trained in space {meta['space']}, the problem searches "
                               f"{space.name!r} [{space.low}, {space.high}]^{space.dim}")
        rollouts = min(rollouts, problem.budget // cfg.horizon)
        if rollouts < 1:
            raise InvphysError(f"gc_ppo needs a budget of at least T = {cfg.horizon} evaluations")
        tracker = Tracker(problem)
        scales, kappa = np.asarray(meta["scales"]), cfg.kappa
        target = np.asarray(problem.target, dtype=np.float64).reshape(-1)

        def record(s: np.ndarray, y: np.ndarray, r: np.ndarray) -> None:
            tracker.record(s, y, np.asarray(problem.objective(y), dtype=np.float64).reshape(-1))

        pen = problem.info.get("uncertainty")  # a penalised problem (penalised_problem): same score as in training

        def score(y: np.ndarray, g: np.ndarray | None) -> np.ndarray:
            r = recovery_reward(y, g, scales, kappa)
            return r if pen is None else np.asarray(r, dtype=np.float64) - pen.penalty(y)

        task = InverseTask(low=space.low, high=space.high, dim=space.dim, predict=problem.predict,
                           score=score,
                           feature_mean=np.asarray(meta["feature_mean"]), feature_std=np.asarray(meta["feature_std"]),
                           horizon=cfg.horizon, step_scale=cfg.step_scale, start=np.asarray(meta["start"]),
                           start_features=np.asarray(meta["start_features"]),
                           goal_sampler=lambda rng, n: np.broadcast_to(target, (n, target.size)).copy(),
                           on_evaluate=record)
        if rollouts > 1:
            import torch

            torch.manual_seed(int(problem.seed))
        batch = EpisodeBatch(task, rollouts, np.random.default_rng(problem.seed))
        batch.reset(goals=target[None, :])
        run_rollouts(self.model, batch, n_deterministic=1)
        return tracker.result(rollouts=rollouts)

    # -- persistence ---------------------------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        """Write ``policy.npz`` (the SB3 policy's state dict as tensors) and ``gc_ppo.json`` (config, feature
        statistics, space, metrics). Nothing is pickled; the optimiser's state is not kept (see :meth:`load`)."""
        if self.model is None:
            raise InvphysError("gc_ppo: nothing to save, the policy is not trained")
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        arrays = {k: v.detach().cpu().numpy() for k, v in self.model.policy.state_dict().items()}
        with open(d / POLICY_FILE, "wb") as fh:  # a handle keeps the name (np.savez appends no ".npz")
            np.savez(fh, **arrays)  # type: ignore[arg-type]
        (d / CONFIG_FILE).write_text(json.dumps(
            {"format": SAVE_FORMAT, "config": self.config.model_dump(), "meta": self.meta, "metrics": self.metrics},
            indent=2))
        if (d / LEGACY_FILE).exists():  # a re-save over an older (cloudpickled) save
            (d / LEGACY_FILE).unlink()
        return d

    @classmethod
    def load(cls, directory: str | Path) -> GoalConditionedPPO:
        """A policy saved by :meth:`save` (identical actions): PPO is rebuilt from the config and the saved
        space, and only the policy's tensors are loaded (``allow_pickle=False``, strict names and shapes).
        Nothing is unpickled: an older save holding only SB3's ``policy.zip`` (cloudpickle) is refused.
        The rebuilt PPO has a fresh optimiser: it acts like the saved one; training it further starts Adam anew.
        """
        d = Path(directory)
        if not (d / CONFIG_FILE).is_file():
            raise InvphysError(f"no saved gc_ppo policy in {d} (expected {CONFIG_FILE} and {POLICY_FILE})")
        if not (d / POLICY_FILE).is_file():
            if (d / LEGACY_FILE).is_file():
                raise LegacyPickleError(d / LEGACY_FILE)
            raise InvphysError(f"no saved gc_ppo policy in {d} (expected {CONFIG_FILE} and {POLICY_FILE})")
        saved = read_json_mapping(d / CONFIG_FILE)
        try:
            opt = cls(cls.Config(**saved["config"]))
            opt.meta = dict(saved["meta"])
            sp = opt.meta["space"]
            dim, n_feat = int(sp["dim"]), len(opt.meta["feature_mean"])
            low, high = float(sp["low"]), float(sp["high"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InvphysError(f"{d / CONFIG_FILE}: not a gc_ppo save this invphys reads ({first_line(exc)})") from None
        metrics = saved.get("metrics")
        opt.metrics = dict(metrics) if isinstance(metrics, dict) else {}
        state = read_weights_npz(d / POLICY_FILE)
        opt._check_size(dim, n_feat, state, d / POLICY_FILE)
        opt.model = opt._rebuild(dim, n_feat, low, high, state, d / POLICY_FILE)
        return opt

    def _check_size(self, dim: int, n_feat: int, state: dict[str, np.ndarray], where: Path) -> None:
        """Refuse, before building anything, a config whose policy and value networks would not hold exactly
        the saved numbers (a hostile ``net_arch`` cannot make PPO allocate more than the file holds)."""
        widths = [dim + 2 * n_feat + 2, *self.config.net_arch]
        mlp = sum(a * b + b for a, b in itertools.pairwise(widths))
        need = 2 * mlp + (widths[-1] * dim + dim) + (widths[-1] + 1) + dim  # pi, vf, action and value heads, log_std
        have = sum(int(v.size) for v in state.values())
        if dim < 1 or n_feat < 1 or need != have:
            raise InvphysError(f"{where}: the weights do not fit the saved config (net_arch {self.config.net_arch} "
                               f"for {dim} actions and {n_feat} features needs {need:,} numbers, the file holds "
                               f"{have:,})")

    def _rebuild(self, dim: int, n_feat: int, low: float, high: float, state: dict[str, np.ndarray],
                 where: Path) -> Any:
        """A PPO with the trained policy's spaces and architecture, holding the saved tensors."""
        import random

        import torch

        from invphys.envs.vec import InverseVecEnv

        cfg = self.config
        try:
            task = self._task(dim, n_feat, low, high)
        except (KeyError, ValueError, TypeError, InvphysError) as exc:
            raise InvphysError(f"{where.parent / CONFIG_FILE}: the saved episode (meta) does not fit a {dim}-dimensional "
                               f"space and {n_feat} features ({first_line(exc)})") from None
        threads, states = torch.get_num_threads(), (torch.get_rng_state(), np.random.get_state(), random.getstate())
        try:  # building PPO seeds the global RNGs and sets torch's threads: leave the caller's as they were
            # acting only: one env and a minimal rollout buffer (a saved n_steps x n_envs is never allocated)
            small = cfg.model_copy(update={"n_envs": 1, "n_steps": 2, "batch_size": 2, "torch_threads": None})
            model = make_ppo(InverseVecEnv(task, 1, 0), small, int(cfg.seed or 0))
        except (ValueError, TypeError, RuntimeError) as exc:  # settings PPO itself refuses (a negative seed, ...)
            raise InvphysError(f"{where.parent / CONFIG_FILE}: PPO cannot be rebuilt from the saved config "
                               f"({first_line(exc)})") from None
        finally:
            torch.set_num_threads(threads)
            torch.set_rng_state(states[0])
            np.random.set_state(states[1])
            random.setstate(states[2])
        check_state(model.policy.state_dict(), state, where, "the saved config")
        model.policy.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()}, strict=True)
        model.policy.set_training_mode(False)
        return model

    def _task(self, dim: int, n_feat: int, low: float, high: float) -> Any:
        """The saved episode (spaces, feature statistics, start) without a surrogate: for acting only."""
        from invphys.envs.task import InverseTask

        meta, cfg = self.meta, self.config

        def no_predict(*args: Any) -> np.ndarray:
            raise InvphysError("a loaded gc_ppo policy has no surrogate to train with")

        def vector(key: str, n: int) -> np.ndarray:
            v = np.asarray(meta[key], dtype=np.float64).reshape(n)
            if not np.all(np.isfinite(v)):
                raise ValueError(f"{key} is not finite")
            return v

        if not (np.isfinite(low) and np.isfinite(high) and low < high):
            raise ValueError(f"space [{low}, {high}]")
        return InverseTask(low=low, high=high, dim=dim, predict=no_predict, score=no_predict,
                           feature_mean=vector("feature_mean", n_feat), feature_std=vector("feature_std", n_feat),
                           horizon=cfg.horizon, step_scale=cfg.step_scale, start=vector("start", dim),
                           start_features=vector("start_features", n_feat),
                           goal_sampler=lambda rng, n: np.zeros((n, n_feat)))

    @classmethod
    def load_legacy_pickle(cls, directory: str | Path) -> GoalConditionedPPO:
        """Load an older save (SB3's ``policy.zip``). RUNS CODE stored in the file (cloudpickle): only for
        files you trust (``invphys export --upgrade ... --trust-pickles`` calls this once, then :meth:`save`)."""
        from stable_baselines3 import PPO

        d = Path(directory)
        saved = read_json_mapping(d / CONFIG_FILE)
        opt = cls(cls.Config(**saved["config"]))
        opt.meta, opt.metrics = saved["meta"], saved.get("metrics", {})
        opt.model = PPO.load(d / LEGACY_FILE, device=opt.config.device)
        return opt


POLICY_FILE = "policy.npz"
CONFIG_FILE = "gc_ppo.json"
LEGACY_FILE = "policy.zip"
#: 2: the policy's tensors in policy.npz (no pickle); 1 (no "format" key): SB3's cloudpickled policy.zip
SAVE_FORMAT = 2
