"""stable-baselines3's logger, writing to a :class:`~invphys.tracking.base.Tracker`.

SB3 dumps its key-values (``rollout/ep_rew_mean``, ``train/value_loss``, ``time/fps``, ...) once per
rollout at ``step = num_timesteps``; :func:`attach` routes them to the run's tracker, so PPO learning
curves land in TensorBoard or MLflow beside the surrogate's. Without a tracker it still installs a
logger that writes nowhere: SB3's default makes an empty ``SB3-<time>`` folder in the system's temp
directory on every ``learn()``, outside the output directory the user named. Imports stable-baselines3 at top level:
import this module only where SB3 is used.
"""

from __future__ import annotations

from typing import Any

from stable_baselines3.common.logger import KVWriter, Logger

from invphys.tracking.base import Tracker


class TrackerOutputFormat(KVWriter):
    """An SB3 output format that logs every numeric key-value to a tracker."""

    def __init__(self, tracker: Tracker) -> None:
        self.tracker = tracker

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        numbers = {k: v for k, v in key_values.items() if "tensorboard" not in (key_excluded.get(k) or ())}
        self.tracker.log_scalars(numbers, int(step))
        self.tracker.flush()

    def close(self) -> None:
        self.tracker.flush()


def attach(model: Any, tracker: Tracker | None) -> None:
    """Send ``model``'s (an SB3 algorithm's) logs to ``tracker``; for ``None``, to nowhere (no temp folder)."""
    formats = [] if tracker is None else [TrackerOutputFormat(tracker)]
    model.set_logger(Logger(folder=None, output_formats=formats))
