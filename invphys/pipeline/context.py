"""The typed context every stage's ``run(ctx)`` receives: the spec, the run directory, the plugins,
the run's tracker, and loaders for earlier stages' artifacts (each loaded once per stage).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.spec import ExperimentSpec
from invphys.tracking import NullTracker, Tracker

#: a finished stage's record: the fingerprint of the inputs it used (see :mod:`invphys.pipeline.runner`)
DONE_FILE = "DONE.json"


@dataclass
class StageContext:
    """What a stage receives: the spec, where to write, and loaders for earlier stages' artifacts."""

    spec: ExperimentSpec
    out: Path
    stage: str
    registry: Any
    console: Any = None
    progress: bool = True
    #: the run's tracker (TensorBoard, MLflow or none): training curves and final metrics go there
    tracker: Tracker = field(default_factory=NullTracker)
    _cache: dict[str, Any] = field(default_factory=dict)

    @property
    def seed(self) -> int:
        return self.spec.seed

    @property
    def stage_dir(self) -> Path:
        d = self.out / self.stage
        d.mkdir(parents=True, exist_ok=True)
        return d

    def stage_dir_of(self, stage: str) -> Path:
        return self.out / stage

    def finished(self, stage: str) -> bool:
        """Whether ``stage`` has finished in this run directory (its :data:`DONE_FILE` is written)."""
        return (self.stage_dir_of(stage) / DONE_FILE).is_file()

    @property
    def logger(self) -> logging.Logger:
        """``invphys.pipeline.stages.<stage>``: the stage's standard-library logger."""
        return logging.getLogger(f"invphys.pipeline.stages.{self.stage}")

    def log(self, message: str, level: int = logging.INFO) -> None:
        """Log ``<stage>: message`` on the stage's logger."""
        self.logger.log(level, "%s: %s", self.stage, message)

    # -- plugins -------------------------------------------------------------------------------
    def simulator(self) -> Any:
        if "simulator" not in self._cache:
            self._cache["simulator"] = self.registry.create("simulator", self.spec.simulator)
        return self._cache["simulator"]

    def extractor_block(self) -> dict[str, Any]:
        """The feature-extractor block: the spec's, or the simulator's default extractor."""
        if self.spec.features is not None:
            return dict(self.spec.features)
        default = self.simulator().default_feature_extractor()
        if default is None:
            raise InvphysError("the spec has no 'features' block and the simulator names no default extractor")
        return {"type": default}

    def extractor(self) -> Any:
        if "extractor" not in self._cache:
            self._cache["extractor"] = self.registry.create("feature_extractor", self.extractor_block())
        return self._cache["extractor"]

    # -- data ----------------------------------------------------------------------------------
    def dataset_path(self) -> Path:
        """``dataset.path`` when set (and present, or ``if_missing: error``), else ``OUT/dataset/store``."""
        ds = self.spec.dataset
        if ds.path and (Path(ds.path).exists() or ds.if_missing == "error"):
            return Path(ds.path)
        return self.stage_dir_of("dataset") / "store"

    def uses_existing_dataset(self) -> bool:
        """True when the spec names an existing dataset store (nothing to generate)."""
        path = self.spec.dataset.path
        return path is not None and self.dataset_path() == Path(path)

    def dataset(self) -> Any:
        """The dataset's arrays (``DatasetArrays``): the dataset stage's store, or ``dataset.path``,
        followed by the rows of ``dataset.extra_train`` (see :meth:`split`)."""
        if "dataset" not in self._cache:
            from invphys.core.dataset import DatasetStore
            from invphys.core.dataset_union import check_extra_stores, join_for_training

            path = self.dataset_path()
            if not path.exists():
                raise InvphysError(f"no dataset at {path}: run the 'dataset' stage or set dataset.path")
            primary = DatasetStore(path).arrays(ok_only=True)
            extras = self.spec.dataset.extra_train
            if extras:
                check_extra_stores(path, [e.path for e in extras])
            self._cache["dataset_primary_rows"] = len(primary)
            self._cache["dataset"] = join_for_training(
                primary, [DatasetStore(e.path).arrays(ok_only=True, first_ok=e.rows) for e in extras])
        return self._cache["dataset"]

    def primary_rows(self) -> int:
        """How many of :meth:`dataset`'s rows are ``dataset.path``'s (the ``extra_train`` rows follow them)."""
        n_all = len(self.dataset().theta)
        return int(self._cache.get("dataset_primary_rows", n_all))

    def split(self) -> tuple[np.ndarray, np.ndarray]:
        """(train_idx, test_idx) of the dataset's ok rows, deterministic by seed and test_fraction.

        The split is drawn over the primary store's rows only; rows of ``dataset.extra_train`` stores
        (after them in :meth:`dataset`; an entry's first ``rows`` ok rows where it caps them) all join the
        training split.
        """
        n_all, n = len(self.dataset().theta), self.primary_rows()
        rng = np.random.default_rng(self.spec.seed)
        perm = rng.permutation(n)
        n_test = max(1, round(n * self.spec.dataset.test_fraction))
        train = np.concatenate([np.sort(perm[n_test:]), np.arange(n, n_all)])
        return train, np.sort(perm[:n_test])

    def data_fingerprint(self) -> str:
        """The content fingerprint of the data the stages read: the store's, plus each extra store's (of
        its first ``rows`` ok rows alone where the entry caps them: growing that store changes nothing)."""
        from invphys.pipeline.cache import data_fingerprint

        own = data_fingerprint(self.dataset_path())
        extras = [data_fingerprint(Path(e.path), e.rows) for e in self.spec.dataset.extra_train]
        return "+".join([own, *extras])

    def scales(self) -> np.ndarray:
        """The paper's per-feature scales s_k = p95 - p5 over the training split of ``dataset.path``.

        Rows of ``dataset.extra_train`` stores do not count: the scales pick the farthest-point targets and
        score every answer, so a data-scale comparison keeps the same targets and the same yardstick.
        """
        from invphys.core.objectives import percentile_scales

        train, _ = self.split()
        return percentile_scales(self.dataset().y[train[train < self.primary_rows()]])

    def surrogate(self) -> Any:
        if "surrogate" not in self._cache:
            cls = self.registry.get("surrogate", self.spec.surrogate["type"])  # type: ignore[index]
            self._cache["surrogate"] = cls.load(self.stage_dir_of("train") / "surrogate")
        return self._cache["surrogate"]

    def latent(self, label: str) -> Any:
        key = f"latent:{label}"
        if key not in self._cache:
            block = self.spec.latent_models[label]
            cls = self.registry.get("latent_model", block["type"])
            self._cache[key] = cls.load(self.stage_dir_of("train") / "latent" / label)
        return self._cache[key]
