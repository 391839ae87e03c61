"""``tracker: mlflow``: one MLflow run per invphys run (``pip install "invphys[mlflow]"``).

Uses :class:`mlflow.tracking.MlflowClient` explicitly (no global active run), so that two runs in one
process never mix. The store is ``tracking_uri``, else ``$MLFLOW_TRACKING_URI``, else a SQLite file
``OUT/mlflow.db`` with artifacts in ``OUT/mlartifacts/`` (``mlflow ui --backend-store-uri
sqlite:///OUT/mlflow.db`` shows it).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from invphys.core.errors import InvphysError
from invphys.tracking.base import Tracker

log = logging.getLogger(__name__)

#: most metrics one ``log_batch`` call takes (MLflow's limit)
BATCH = 1000
#: most params one ``log_batch`` call takes, and the longest param key and value MLflow stores
PARAM_BATCH = 100
MAX_PARAM_KEY = 250
MAX_PARAM_VALUE = 6000

_MISSING = 'tracker: mlflow needs the mlflow client: pip install "invphys[mlflow]"'


class MLflowTracker(Tracker):
    """Logs scalars as MLflow metrics (``/`` kept in keys), text and artifacts as run artifacts.

    Scalars are buffered and sent with ``log_batch`` on :meth:`flush` (every model's fit, every PPO
    rollout and every stage flush) or every :data:`BATCH` values: one store transaction per batch,
    not per value.
    """

    name = "mlflow"

    def __init__(self, run_dir: str | Path, tracking_uri: str | None = None, experiment: str = "invphys",
                 run_name: str | None = None) -> None:
        try:
            from mlflow.tracking import MlflowClient
        except ImportError as exc:
            raise InvphysError(_MISSING) from exc
        quiet_backend_logs()
        run_dir = Path(run_dir).resolve()
        run_dir.mkdir(parents=True, exist_ok=True)
        self.tracking_uri = (tracking_uri or os.environ.get("MLFLOW_TRACKING_URI")
                             or f"sqlite:///{run_dir / 'mlflow.db'}")
        self.client = MlflowClient(tracking_uri=self.tracking_uri)
        found = self.client.get_experiment_by_name(experiment)
        if found is not None:
            experiment_id = found.experiment_id
        else:
            location = (run_dir / "mlartifacts").as_uri() if self.tracking_uri.startswith("sqlite:") else None
            experiment_id = self.client.create_experiment(experiment, artifact_location=location)
        self.run_id: str = self.client.create_run(experiment_id, run_name=run_name).info.run_id
        self._closed = False
        self._pending: list[Any] = []
        self._artifacts: set[str] = set()
        log.info("MLflow run %s in %s", self.run_id, self.tracking_uri)

    def log_scalar(self, tag: str, value: float, step: int) -> None:
        from mlflow.entities import Metric

        self._pending.append(Metric(_key(tag), float(value), int(time.time() * 1000), int(step)))
        if len(self._pending) >= BATCH:
            self.flush()

    def flush(self) -> None:
        while self._pending:
            batch, self._pending = self._pending[:BATCH], self._pending[BATCH:]
            self.client.log_batch(self.run_id, metrics=batch)

    def log_text(self, tag: str, text: str) -> None:
        self.client.log_text(self.run_id, text, f"text/{_key(tag)}.md")

    def log_artifact(self, path: str | Path, name: str | None = None) -> None:
        path = Path(path)
        folder = str(Path(name).parent) if name and str(Path(name).parent) != "." else None
        if path.is_dir():
            self.client.log_artifacts(self.run_id, str(path), name or path.name)
        else:
            self.client.log_artifact(self.run_id, str(path), folder)
            self._artifacts.add(f"{folder}/{path.name}" if folder else path.name)

    def log_params(self, params: Mapping[str, Any]) -> None:
        """The settings as MLflow params (keys sanitised like metric keys, values as text, cut to MLflow's
        limits), in batches of :data:`PARAM_BATCH`."""
        from mlflow.entities import Param

        items = [Param(_key(k)[:MAX_PARAM_KEY], _param_text(v)) for k, v in params.items()]
        for start in range(0, len(items), PARAM_BATCH):
            self.client.log_batch(self.run_id, params=items[start:start + PARAM_BATCH])

    def log_image(self, tag: str, path: str | Path, step: int = 0) -> None:
        """A figure as an artifact at ``<tag>.png`` (once: a file already attached there is not copied again)."""
        path = Path(path)
        name = f"{_key(tag)}{path.suffix}"
        if name not in self._artifacts:
            folder = str(Path(name).parent)
            self.client.log_artifact(self.run_id, str(path), None if folder == "." else folder)
            self._artifacts.add(name)

    def close(self) -> None:
        if not self._closed:
            self.flush()
            self.client.set_terminated(self.run_id)
            self._closed = True

    @property
    def run(self) -> Any:
        return self.client.get_run(self.run_id)


def _param_text(value: Any) -> str:
    text = "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)
    return text if len(text) <= MAX_PARAM_VALUE else text[:MAX_PARAM_VALUE - 3] + "..."


def quiet_backend_logs() -> None:
    """MLflow's and Alembic's INFO lines (database set-up, migrations) only when invphys logs debug lines:
    MLflow sets its loggers to INFO when imported, so this runs after the import."""
    ours = logging.getLogger("invphys").getEffectiveLevel()
    if ours <= logging.DEBUG or os.environ.get("INVPHYS_DEBUG"):
        return
    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(max(ours, logging.WARNING))


def _key(tag: str) -> str:
    """MLflow metric keys allow alphanumerics, ``_-./`` and spaces; anything else becomes ``_``."""
    return "".join(c if c.isalnum() or c in "_-./ " else "_" for c in tag)
