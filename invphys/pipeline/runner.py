"""Runs the stages a spec names, caching each stage's artifacts under the run directory.

Layout of a run directory ``OUT``::

    OUT/spec.yaml                  the spec as run
    OUT/<stage>/                   the stage's artifacts
    OUT/<stage>/summary.json       what the stage returned
    OUT/<stage>/DONE.json          fingerprint of the inputs the stage used

A stage is skipped when its ``DONE.json`` fingerprint equals the key of what it consumes now
(:mod:`invphys.pipeline.cache`): the spec sections it names in ``DEPENDS_ON``, the versions of the
plugins they use, the dataset's content fingerprint, and the keys and run ids of the stages before it.
Change a section, add or lose dataset rows, upgrade a plugin or re-run an earlier stage, and that stage
and every later stage run again (the runner says why); kill a run, and a re-run resumes at the first
stage without a matching marker (the dataset stage also resumes inside itself).
"""

from __future__ import annotations

import hashlib
import importlib
import json
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import yaml

from invphys.core.atomic import output_directory, write_json
from invphys.core.errors import InvphysError, did_you_mean
from invphys.core.spec import STAGES, ExperimentSpec, check_output_directory, load_spec
from invphys.pipeline.context import DONE_FILE, StageContext

__all__ = ["StageContext", "fingerprint", "run_spec", "stage_module"]

SUMMARY_FILE = "summary.json"
#: most figures of one stage sent to the tracker as images (its top level, then one folder down)
MAX_IMAGES = 64


def fingerprint(obj: Any) -> str:
    """A short stable hash of a JSON-able object."""
    blob = json.dumps(obj, sort_keys=True, default=str, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def stage_module(stage: str) -> Any:
    """The module implementing a stage (``invphys.pipeline.stages.<stage>``)."""
    return importlib.import_module(f"invphys.pipeline.stages.{stage}")


def run_spec(spec: str | Path | ExperimentSpec, out: str | Path, stages: Sequence[str] | None = None,
             force: Sequence[str] = (), progress: bool = True, console: Any = None,
             registry: Any = None,
             on_stage: Callable[[str, str, dict[str, Any] | None], None] | None = None,
             tracker: Any = None, quiet: bool = False) -> dict[str, Any]:
    """Run the spec's stages (or ``stages``) into ``out``; returns ``{stage: summary}``.

    ``out`` is checked before anything is written (:func:`~invphys.core.spec.check_output_directory`):
    not a file, not under one, not a symlink loop, not in or under a dataset store or an inverter bundle.
    ``quiet`` leaves out the runner's own information lines (why a stage re-runs); warnings stay.

    ``force`` names stages to re-run even when cached. ``on_stage(stage, status, summary)`` is called
    with status ``"cached"``, ``"start"`` or ``"done"``. ``tracker`` (a :class:`~invphys.tracking.Tracker`)
    overrides the spec's ``tracker`` setting; the run's tracker receives every training curve and, after
    each stage that ran, its summary's numbers (``<stage>/...``) and its files as artifacts.
    """
    from rich.console import Console

    from invphys import registry as registry_module
    from invphys.pipeline.artifacts import check_pools
    from invphys.tracking import create_tracker

    if not isinstance(spec, ExperimentSpec):
        spec = load_spec(spec, registry=registry)
    reg = registry or registry_module.default_registry()
    console = console or Console(stderr=True)
    out = Path(out)
    spec_stages = spec.stages or []
    selected = list(stages) if stages else list(spec_stages)
    for s in [*selected, *force]:
        if s not in STAGES:
            raise InvphysError(f"unknown stage {s!r}.{did_you_mean(s, STAGES)} Stages: {', '.join(STAGES)}")
    check_output_directory(out)
    check_pools(spec)
    output_directory(out)
    (out / "spec.yaml").write_text(yaml.safe_dump(spec.model_dump(mode="json", by_alias=True), sort_keys=False))
    summaries: dict[str, Any] = {}
    own_tracker = tracker is None
    tracker = tracker or create_tracker(getattr(spec, "tracker", None), out, run_name=spec.name)
    try:
        if hasattr(tracker, "log_params"):  # a duck-typed tracker of older code may lack it
            tracker.log_params(spec_params(spec))
        _run_stages(spec, out, selected, force, progress, console, reg, on_stage, tracker, summaries, quiet)
    finally:
        if own_tracker:
            tracker.close()
    return summaries


def _run_stages(spec: ExperimentSpec, out: Path, selected: list[str], force: Sequence[str], progress: bool,
                console: Any, reg: Any, on_stage: Any, tracker: Any, summaries: dict[str, Any],
                quiet: bool = False) -> None:
    from invphys.pipeline import cache

    spec_stages = spec.stages or []
    upstream: dict[str, Any] = {}
    legacy_upstream: dict[str, Any] = {}  # the same chain with execution settings in the keys (older runs)
    stale: list[str] = []  # earlier stages not run now whose results no longer match the spec or data: why
    for stage in STAGES:
        if stage not in spec_stages and stage not in selected:
            continue
        module = stage_module(stage)
        sections = tuple(getattr(module, "DEPENDS_ON", ()))
        ctx = StageContext(spec=spec, out=out, stage=stage, registry=reg, console=console, progress=progress,
                           tracker=tracker)
        done_path = out / stage / DONE_FILE
        done = cache.read_done(done_path)
        shared = {"plugins": cache.plugin_versions(spec, sections, reg),
                  "data": ctx.data_fingerprint() if stage in cache.DATA_STAGES else ""}
        components = {"spec": cache.digest(cache.key_inputs(spec, sections, reg)), **shared,
                      "upstream": cache.digest(upstream)}
        legacy = {"spec": cache.digest(cache.key_inputs(spec, sections, reg, execution=True)), **shared,
                  "upstream": cache.digest(legacy_upstream)}
        fp = cache.digest({"components": components, "stage": stage})
        legacy_fp = cache.digest({"components": legacy, "stage": stage})
        current = done is not None and done.get("fingerprint") in (fp, legacy_fp)
        run_id = done.get("run_id") if current and done is not None else None
        upstream = {**upstream, stage: [fp, run_id]}
        legacy_upstream = {**legacy_upstream, stage: [legacy_fp, run_id]}
        if stage not in selected:
            if done is not None and not current:
                stale.append(f"{stage} ({cache.stale_reason(done, components)})")
            continue
        if stale:  # cached or not, this stage's result rests on them
            console.print(f"[yellow]warning:[/] {stage}: reads results that no longer match the spec or data: "
                          f"{', '.join(stale)}; re-run {'them' if len(stale) > 1 else 'it'} (--stage) for a "
                          f"current {stage}")
        if stage not in force and current:
            summary = cache.read_done(out / stage / SUMMARY_FILE)
            if summary is not None:
                _refresh(module, ctx, done_path, quiet)
                summaries[stage] = summary
                if on_stage:
                    on_stage(stage, "cached", summary)
                continue
        if done is not None and stage not in force and not quiet:
            console.print(f"[dim]{stage}:[/] re-running: {cache.stale_reason(done, components)}")
        done_path.unlink(missing_ok=True)
        if on_stage:
            on_stage(stage, "start", None)
        t0 = time.perf_counter()
        summary = module.run(ctx) or {}
        summary = {**summary, "wall_time_s": round(time.perf_counter() - t0, 3)}
        write_json(out / stage / SUMMARY_FILE, summary)
        if stage == "dataset":  # the key records the data as made (a re-run then finds it unchanged)
            components["data"] = ctx.data_fingerprint()
            fp = cache.digest({"components": components, "stage": stage})
        run_id = uuid.uuid4().hex[:12]
        write_json(done_path, {"fingerprint": fp, "components": components, "run_id": run_id,
                               "finished_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                               **_refresh_key(module, spec)})
        upstream[stage] = [fp, run_id]
        legacy_upstream[stage] = [None, run_id]  # a re-run stage has no legacy key: later stages re-run too
        summaries[stage] = summary
        _track_stage(tracker, stage, out / stage, summary)
        if on_stage:
            on_stage(stage, "done", summary)


def _refresh_key(module: Any, spec: ExperimentSpec) -> dict[str, str]:
    """``{"refresh": digest}`` of the spec sections a stage's output reads without them keying its work
    (``REFRESHED_BY``: e.g. the bundle's description and pools), or ``{}`` for a stage without any."""
    from invphys.pipeline import cache

    sections = tuple(getattr(module, "REFRESHED_BY", ()))
    return {"refresh": cache.digest(spec.section_dump(sections))} if sections else {}


def _refresh(module: Any, ctx: StageContext, done_path: Path, quiet: bool) -> None:
    """A cached stage whose ``REFRESHED_BY`` sections changed since it ran rewrites what they shape
    (``module.refresh``, seconds: e.g. the run's bundle with new pools), without re-running its work."""
    from invphys.pipeline import cache

    key = _refresh_key(module, ctx.spec)
    if not key:
        return
    done = cache.read_done(done_path) or {}
    if done.get("refresh") == key["refresh"]:
        return
    if module.refresh(ctx) and not quiet:
        ctx.console.print(f"[dim]{ctx.stage}:[/] cached; its bundle rewritten for the spec's "
                          f"{', '.join(module.REFRESHED_BY)}")
    write_json(done_path, {**done, **key})


def spec_params(spec: ExperimentSpec) -> dict[str, Any]:
    """The spec's settings as flat ``section.key`` parameters (what a tracker records to compare runs by)."""
    from invphys.tracking import flatten_params

    data = spec.model_dump(mode="json", by_alias=True, exclude={"description"})
    return flatten_params(data)


def _track_stage(tracker: Any, stage: str, stage_dir: Path, summary: dict[str, Any]) -> None:
    """A finished stage's summary numbers (``<stage>/...``, step 0), top-level files as artifacts and its
    figures (``.png``) as images."""
    tracker.log_scalars(summary, step=0, prefix=stage)
    for path in sorted(stage_dir.iterdir()):
        if path.is_file() and path.name != DONE_FILE:
            tracker.log_artifact(path, f"{stage}/{path.name}")
    figures = [*sorted(stage_dir.glob("*.png")), *sorted(stage_dir.glob("*/*.png"))][:MAX_IMAGES]
    for path in figures if hasattr(tracker, "log_image") else []:
        tracker.log_image(f"{stage}/{path.relative_to(stage_dir).with_suffix('').as_posix()}", path)
    tracker.flush()
