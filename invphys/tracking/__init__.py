"""Experiment tracking: every training curve, final metric and artifact of a run, in one place.

The spec's ``tracker`` setting picks where they go:

* ``tensorboard`` (default): event files in ``OUT/tensorboard/`` (``tensorboard --logdir OUT/tensorboard``);
* ``mlflow``: an MLflow run (``pip install "invphys[mlflow]"``); ``tracking_uri`` defaults to
  ``$MLFLOW_TRACKING_URI``, else a SQLite store ``OUT/mlflow.db``;
* ``none``: nothing.

The runner creates one tracker per run and passes it down (:attr:`StageContext.tracker`); models take
``fit(..., tracker=...)``, optimisers find it in ``problem.info["tracker"]`` or ``prepare(..., tracker=...)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from invphys.core.errors import InvphysError, did_you_mean
from invphys.tracking.base import NullTracker, ScopedTracker, Tracker, flatten_numbers, flatten_params

__all__ = ["TRACKERS", "NullTracker", "ScopedTracker", "Tracker", "create_tracker", "flatten_numbers", "flatten_params"]

#: the values of the ``tracker`` setting
TRACKERS: tuple[str, ...] = ("tensorboard", "mlflow", "none")


def create_tracker(setting: Any, run_dir: str | Path, run_name: str | None = None) -> Tracker:
    """The tracker a ``tracker`` setting names, writing under ``run_dir``.

    ``setting`` is a name (``"tensorboard"``), a mapping or an object with ``type`` and the optional
    MLflow fields ``tracking_uri`` and ``experiment``; ``None`` means the default (TensorBoard).
    """
    fields = _fields(setting)
    kind = fields.get("type") or "tensorboard"
    run_dir = Path(run_dir)
    if kind == "none":
        return NullTracker()
    if kind == "tensorboard":
        from invphys.tracking.tensorboard import LOGDIR, TensorBoardTracker

        return TensorBoardTracker(run_dir / LOGDIR)
    if kind == "mlflow":
        from invphys.tracking.mlflow_tracker import MLflowTracker

        return MLflowTracker(run_dir, tracking_uri=fields.get("tracking_uri"),
                             experiment=fields.get("experiment") or run_name or "invphys", run_name=run_name)
    raise InvphysError(f"unknown tracker {kind!r}.{did_you_mean(str(kind), TRACKERS)} Trackers: {', '.join(TRACKERS)}")


def _fields(setting: Any) -> dict[str, Any]:
    if setting is None:
        return {}
    if isinstance(setting, str):
        return {"type": setting}
    if isinstance(setting, Mapping):
        return dict(setting)
    if hasattr(setting, "model_dump"):
        return dict(setting.model_dump())
    raise InvphysError(f"tracker: expected a name or a block, got {setting!r}")
