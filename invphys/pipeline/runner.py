"""Runs the stages a spec names, caching each stage's artifacts under the run directory.

Layout of a run directory ``OUT``::

    OUT/spec.yaml                  the spec as run
    OUT/<stage>/                   the stage's artifacts
    OUT/<stage>/summary.json       what the stage returned
    OUT/<stage>/DONE.json          fingerprint of the inputs the stage used

A stage is skipped when its ``DONE.json`` fingerprint equals the fingerprint of its inputs now: the spec
sections it names in ``DEPENDS_ON`` plus the fingerprints of the stages before it. Change a section,
and that stage and every later stage run again; kill a run, and a re-run resumes at the first stage
without a matching marker (the dataset stage also resumes inside itself).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from invphys.core.atomic import write_json
from invphys.core.errors import InvphysError
from invphys.core.spec import STAGES, ExperimentSpec, load_spec

DONE_FILE = "DONE.json"
SUMMARY_FILE = "summary.json"


def fingerprint(obj: Any) -> str:
    """A short stable hash of a JSON-able object."""
    blob = json.dumps(obj, sort_keys=True, default=str, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


@dataclass
class StageContext:
    """What a stage receives: the spec, where to write, and loaders for earlier stages' artifacts."""

    spec: ExperimentSpec
    out: Path
    stage: str
    registry: Any
    console: Any
    progress: bool = True
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

    def log(self, message: str) -> None:
        self.console.print(f"[dim]{self.stage}:[/] {message}")

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
        """The dataset's arrays (``DatasetArrays``): the dataset stage's store, or ``dataset.path``."""
        if "dataset" not in self._cache:
            from invphys.core.dataset import DatasetStore

            path = self.dataset_path()
            if not path.exists():
                raise InvphysError(f"no dataset at {path}: run the 'dataset' stage or set dataset.path")
            self._cache["dataset"] = DatasetStore(path).arrays(ok_only=True)
        return self._cache["dataset"]

    def split(self) -> tuple[np.ndarray, np.ndarray]:
        """(train_idx, test_idx) of the dataset's ok rows, deterministic by seed and test_fraction."""
        n = len(self.dataset().theta)
        rng = np.random.default_rng(self.spec.seed)
        perm = rng.permutation(n)
        n_test = max(1, round(n * self.spec.dataset.test_fraction))
        return np.sort(perm[n_test:]), np.sort(perm[:n_test])

    def scales(self) -> np.ndarray:
        """The paper's per-feature scales s_k = p95 - p5 over the training split."""
        from invphys.core.objectives import percentile_scales

        train, _ = self.split()
        return percentile_scales(self.dataset().y[train])

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


def stage_module(stage: str) -> Any:
    """The module implementing a stage (``invphys.pipeline.stages.<stage>``)."""
    return importlib.import_module(f"invphys.pipeline.stages.{stage}")


def run_spec(spec: str | Path | ExperimentSpec, out: str | Path, stages: Sequence[str] | None = None,
             force: Sequence[str] = (), progress: bool = True, console: Any = None,
             registry: Any = None,
             on_stage: Callable[[str, str, dict[str, Any] | None], None] | None = None) -> dict[str, Any]:
    """Run the spec's stages (or ``stages``) into ``out``; returns ``{stage: summary}``.

    ``force`` names stages to re-run even when cached. ``on_stage(stage, status, summary)`` is called
    with status ``"cached"``, ``"start"`` or ``"done"``.
    """
    from rich.console import Console

    from invphys import registry as registry_module

    if not isinstance(spec, ExperimentSpec):
        spec = load_spec(spec, registry=registry)
    reg = registry or registry_module.default_registry()
    console = console or Console(stderr=True)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "spec.yaml").write_text(yaml.safe_dump(spec.model_dump(mode="json", by_alias=True), sort_keys=False))
    spec_stages = spec.stages or []
    selected = list(stages) if stages else list(spec_stages)
    for s in selected:
        if s not in STAGES:
            raise InvphysError(f"unknown stage {s!r}; stages: {', '.join(STAGES)}")
    summaries: dict[str, Any] = {}
    upstream = ""
    for stage in STAGES:
        if stage not in spec_stages and stage not in selected:
            continue
        module = stage_module(stage)
        inputs = spec.section_dump(getattr(module, "DEPENDS_ON", ()))
        inputs["seed"] = spec.seed
        fp = fingerprint({"inputs": inputs, "upstream": upstream, "stage": stage})
        upstream = fp
        if stage not in selected:
            continue
        done_path = out / stage / DONE_FILE
        if stage not in force and done_path.exists():
            done = json.loads(done_path.read_text())
            if done.get("fingerprint") == fp:
                summary = json.loads((out / stage / SUMMARY_FILE).read_text())
                summaries[stage] = summary
                if on_stage:
                    on_stage(stage, "cached", summary)
                continue
        if done_path.exists():
            done_path.unlink()
        ctx = StageContext(spec=spec, out=out, stage=stage, registry=reg, console=console, progress=progress)
        if on_stage:
            on_stage(stage, "start", None)
        t0 = time.perf_counter()
        summary = module.run(ctx) or {}
        summary = {**summary, "wall_time_s": round(time.perf_counter() - t0, 3)}
        write_json(out / stage / SUMMARY_FILE, summary)
        write_json(done_path, {"fingerprint": fp, "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())})
        summaries[stage] = summary
        if on_stage:
            on_stage(stage, "done", summary)
    return summaries
