"""The files one stage writes and later stages read, and their loaders: stages read each other's output
through this module, never by importing another stage (``tests/test_layers.py`` checks that).

* invert: ``results.json`` (one row per answer) and ``targets.json`` (:func:`load_results`, :func:`summarise`);
* validate: ``validation.json`` and ``evaluation_rows.json`` (:func:`load_validation`,
  :func:`load_evaluation_rows`), and the runs of its first :data:`RENDER_TARGETS` targets kept for the report;
* active: ``rows.json``, ``validation.json`` and ``rounds.json`` (:func:`load_active`);
* the evaluation protocol's baselines, answered once and cached in the asking stage's ``baselines.json``
  (:func:`baselines`: the validate stage, the active stage's start, a report without a validate stage).
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

import numpy as np

from invphys.core.errors import InvphysError

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

#: the invert stage's answers and targets
RESULTS_FILE = "results.json"
TARGETS_FILE = "targets.json"
#: the validate stage's rows, the evaluation protocol's rows and the baselines' answer cache
VALIDATION_FILE = "validation.json"
EVALUATION_ROWS_FILE = "evaluation_rows.json"
BASELINES_FILE = "baselines.json"
#: the validate stage keeps the runs of its first this-many targets for the report's drawings
RENDER_TARGETS = 3
#: the active stage's rounds
ROUNDS_FILE = "rounds.json"


def load_results(ctx: StageContext) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """(rows, targets) written by the invert stage (for the validate, active and report stages)."""
    d = ctx.stage_dir_of("invert")
    if not (d / RESULTS_FILE).is_file():
        raise InvphysError(f"no inversion results in {d}: run the 'invert' stage first")
    return json.loads((d / RESULTS_FILE).read_text()), json.loads((d / TARGETS_FILE).read_text())


def summarise(rows: list[dict[str, Any]], score: str = "r_surrogate") -> dict[str, Any]:
    """Per optimiser label and problem kind: count, mean score, mean evaluations and mean time."""
    out: dict[str, Any] = {}
    for label in dict.fromkeys(r["optimizer"] for r in rows):
        mine = [r for r in rows if r["optimizer"] == label]
        for kind in ("target", "objective"):
            sel = [r for r in mine if r["problem"] == kind]
            if sel:
                vals = np.array([r[score] for r in sel], dtype=np.float64)
                out.setdefault(label, {})[kind] = {
                    "n": len(sel), f"mean_{score}": float(np.nanmean(vals)) if np.isfinite(vals).any() else None,
                    "mean_evaluations": float(np.mean([r["evaluations"] for r in sel])),
                    "mean_time_s": float(np.mean([r["wall_time_s"] for r in sel]))}
    return out


def load_validation(ctx: StageContext) -> list[dict[str, Any]] | None:
    """The validate stage's rows, or None when it has not run."""
    p = ctx.stage_dir_of("validate") / VALIDATION_FILE
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise InvphysError(f"{p} is not valid JSON ({exc}); re-run the validate stage") from exc


def load_evaluation_rows(ctx: StageContext) -> list[dict[str, Any]]:
    """The evaluation's rows written by the validate stage ([] when it has not run)."""
    p = ctx.stage_dir_of("validate") / EVALUATION_ROWS_FILE
    return json.loads(p.read_text()) if p.is_file() else []


def load_active(ctx: StageContext) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
    """(rows, validation rows, rounds) written by the active stage, or empty lists when it has not run."""
    d = ctx.stage_dir_of("active")
    if not ctx.finished("active"):
        return [], [], []
    return (json.loads((d / "rows.json").read_text()), json.loads((d / "validation.json").read_text()),
            json.loads((d / ROUNDS_FILE).read_text()))


def baselines(ctx: StageContext, targets: dict[str, Any]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The spec's baselines fitted on the training partition and answered for every target (cached in the
    calling stage's ``baselines.json``, keyed by what they answer from, the answers' seeding and the versions
    that baselines declare)."""
    from invphys.core.atomic import write_json
    from invphys.evaluation.answers import baseline_rows
    from invphys.pipeline.artifacts import to_params
    from invphys.pipeline.cache import SEEDING
    from invphys.pipeline.context import DONE_FILE
    from invphys.pipeline.runner import fingerprint

    blocks = ctx.spec.evaluation.baselines
    if not blocks:
        return [], {}
    done = ctx.stage_dir_of("train") / DONE_FILE
    # the seeding: answers cached before posterior draws were seeded per target are not served again
    what = {"baselines": blocks, "rows": targets["rows"], "features": targets["features"],
            "dataset": ctx.spec.section_dump(["dataset"]), "seed": ctx.seed,
            "train": done.read_text() if done.is_file() else None, "seeding": SEEDING}
    versions = _own_versions(ctx, blocks)
    if versions:  # only baselines that declare a version: the keys of the others' caches stay as they were
        what["versions"] = versions
    key = fingerprint(what)
    cache = ctx.stage_dir / BASELINES_FILE
    if cache.is_file():
        blob = json.loads(cache.read_text())
        if blob.get("key") == key:
            ctx.log(f"baselines: {', '.join(blocks)} from {cache}")
            return blob["rows"], blob["metrics"]
    data = ctx.dataset()
    train_idx, _ = ctx.split()
    plugins = {label: ctx.registry.create("optimizer", block) for label, block in blocks.items()}
    rows, metrics = baseline_rows(plugins, data.theta[train_idx], data.y[train_idx], ctx.scales(), targets,
                                  ctx.surrogate().predict, to_params(ctx), progress=False, log=ctx.log,
                                  surrogate=ctx.surrogate())
    write_json(cache, {"key": key, "rows": rows, "metrics": metrics})
    return rows, metrics


def _own_versions(ctx: StageContext, blocks: dict[str, Any]) -> dict[str, str]:
    """``{label: version}`` of the baselines whose class declares a ``version`` (bumped when the same
    settings answer differently, e.g. ``corrected_search`` "2": seeded per target)."""
    out = {}
    for label, block in blocks.items():
        try:
            own = getattr(ctx.registry.get("optimizer", block["type"]), "version", None)
        except Exception:  # reported by validation; a key must not fail
            own = None
        if isinstance(own, str):
            out[label] = own
    return out
