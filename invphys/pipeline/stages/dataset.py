"""The ``dataset`` stage: generate (or resume) the spec's dataset, or check an existing one.

Generates into ``OUT/dataset/store`` (:meth:`StageContext.dataset_path`); with ``dataset.path`` set it
generates nothing and summarises that store instead (unless the store is absent and
``dataset.if_missing: generate``, as in the quick start: then it generates ``dataset.n`` runs). A generation stopped early (time limit, SIGTERM,
Ctrl-C) raises :class:`DatasetIncomplete` (a time limit) or :class:`~invphys.core.errors.Interrupted` (a
signal: the CLI prints ``interrupted`` and exits 130) after storing what finished, so the stage is not marked done
and the next ``invphys run`` resumes it.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from invphys.core.errors import Interrupted, InvphysError

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("simulator", "features", "dataset")


class DatasetIncomplete(InvphysError):
    """The dataset stage stopped before every row was stored; re-running resumes it."""


def run(ctx: StageContext) -> dict[str, Any]:
    from invphys.core.dataset import DatasetStore

    spec = ctx.spec
    path = ctx.dataset_path()
    if ctx.uses_existing_dataset():
        info = DatasetStore(path).info()
        ctx.log(f"using the existing dataset {path}: {info['ok']} ok rows, {info['failed']} failed")
        return {"path": str(path), "generated": False, "rows": info["rows"], "ok": info["ok"],
                "failed": info["failed"], "fingerprint": info["fingerprint"]}

    from invphys.data.generate import generate_dataset

    ds = spec.dataset
    summary = generate_dataset(
        path, simulator=spec.simulator, features=spec.features, executor=spec.executor, n=ds.n,
        sampler=ds.sampler, batch_size=ds.batch_size, seed=ds.seed if ds.seed is not None else spec.seed,
        limit_minutes=ds.limit_minutes, spec=spec.model_dump(mode="json", by_alias=True),
        progress=ctx.progress, console=ctx.console, registry=ctx.registry, adaptive=ds.adaptive,
    )
    if summary.stop_reason in ("interrupted", "terminated"):  # Ctrl-C / SIGTERM: the stop the user asked for
        ctx.log(f"stopped ({summary.stop_reason}) with {summary.total_rows} of {summary.requested} rows stored in "
                f"{path}; run again to resume", logging.WARNING)
        raise Interrupted(summary.stop_reason, 130 if summary.stop_reason == "interrupted" else 143)
    if not summary.complete:
        raise DatasetIncomplete(
            f"dataset stage stopped ({summary.stop_reason}) with {summary.total_rows} of {summary.requested} "
            f"rows stored in {path}; run again to resume")
    ctx.log(f"{summary.ran} runs ({summary.ok} ok, {summary.failed} failed) in {summary.wall_s:.1f} s, "
            f"{summary.runs_per_hour:,.0f} runs/h; {summary.already_present} were already stored")
    return {"path": str(path), "generated": True, **summary.to_dict(),
            "fingerprint": DatasetStore(path).arrays(ok_only=True).fingerprint}
