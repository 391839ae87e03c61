"""Built-in optimiser plugins (paper secs. 3.4-3.5 and 4.1).

Listing them is import-cheap: each class imports cma / nevergrad / optuna / stable-baselines3 / torch
inside its methods.
"""

from __future__ import annotations

from invphys.plugins.optimizers.cma_es import CMAES
from invphys.plugins.optimizers.gc_ppo import GoalConditionedPPO
from invphys.plugins.optimizers.nevergrad_opt import NevergradOptimizer
from invphys.plugins.optimizers.optuna_opt import OptunaOptimizer
from invphys.plugins.optimizers.ppo import PPOOptimizer
from invphys.plugins.optimizers.warm_start import WarmStart

OPTIMIZERS: list[type] = [CMAES, NevergradOptimizer, OptunaOptimizer, PPOOptimizer, GoalConditionedPPO, WarmStart]

__all__ = ["CMAES", "OPTIMIZERS", "GoalConditionedPPO", "NevergradOptimizer", "OptunaOptimizer", "PPOOptimizer",
           "WarmStart"]
