"""Stage cache keys: what a stage consumed, so that a changed input re-runs it (and says why).

A stage's key has four parts, each recorded in its ``DONE.json``:

* ``spec``: the spec sections the stage names in ``DEPENDS_ON`` (plus the seed), without the settings
  that only change where or how fast work runs (:func:`key_inputs`);
* ``plugins``: the name, distribution and version of every plugin those sections use and, for a stage
  that reads the dataset's features or the ``features`` section, the feature extractor's identity
  (:func:`extractor_identity`: its registered name, version, settings, feature names and units), so that
  adding units or changing the extractor re-runs the stages that record them (the bundle written by
  ``train`` holds the units);
* ``data``: the dataset's content fingerprint (:meth:`DatasetStore.content_fingerprint`: its
  manifest's checksums), for every stage that reads the dataset;
* ``upstream``: the keys of the stages before it and the run id of each earlier stage's last run
  (re-running ``train`` with ``--force`` re-runs ``invert``).

When a key differs from the recorded one, :func:`stale_reason` names the parts that changed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

#: the stages that read the dataset (and so depend on its content)
DATA_STAGES: tuple[str, ...] = ("dataset", "train", "invert", "validate", "report")


def digest(obj: Any) -> str:
    """A short stable hash of a JSON-able object."""
    blob = json.dumps(obj, sort_keys=True, default=str, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


#: non-plugin spec fields that say how fast work goes, not what it computes (left out of stage keys)
EXECUTION_FIELDS: dict[str, tuple[str, ...]] = {"dataset": ("batch_size", "limit_minutes")}


def key_inputs(spec: Any, sections: tuple[str, ...], registry: Any, execution: bool = False) -> dict[str, Any]:
    """The spec content a stage's key hashes: its ``sections`` and the seed.

    Settings that change where or how fast work runs but not its results are left out (``execution``
    True keeps them: the keys of runs made before 2026-11-26 hashed them, and are still recognised):
    the fields each plugin class lists in ``identity_ignores`` (a simulator's device, batch size and
    scheduling; the validator's batch size and extraction workers) and :data:`EXECUTION_FIELDS`. So a
    run moved to a GPU, or given bigger batches, keeps its cached stages.
    """
    inputs = spec.section_dump(sections)
    inputs["seed"] = spec.seed
    if execution:
        return inputs
    for section, names in EXECUTION_FIELDS.items():
        block = inputs.get(section)
        if isinstance(block, dict):
            for name in names:
                block.pop(name, None)
    for path, kind, _ in spec.plugin_blocks():
        block = _at(inputs, path)
        if not isinstance(block, dict):
            continue
        try:
            cls = registry.info(kind, str(block.get("type"))).cls
        except Exception:  # reported by validation; a key must not fail
            cls = None
        canonical = getattr(cls, "canonical_block", None)
        if canonical is not None:  # one form per config (e.g. an ``engine:`` block folded into flat keys)
            folded = canonical(block)
            block.clear()
            block.update(folded)
        for name in getattr(cls, "identity_ignores", ()):
            block.pop(name, None)
    return inputs


def _at(tree: dict[str, Any], path: str) -> Any:
    """``tree["a"]["b"]`` for ``path`` "a.b" (None where absent)."""
    node: Any = tree
    for part in path.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return node


#: the entry of :func:`plugin_versions` that holds the feature extractor's identity
EXTRACTOR_ENTRY = "features (extractor)"
#: sections whose stages read what the extractor computed or describes (feature columns, their units)
EXTRACTOR_SECTIONS: tuple[str, ...] = ("features", "dataset")


def extractor_identity(spec: Any, registry: Any) -> str:
    """``"name@version/<digest>"`` of the extractor the run uses (the ``features`` block, else the simulator's
    default): the digest covers its settings, feature names and ``feature_units``; ``"?"`` when it cannot be
    built (validation reports that; a key must not fail)."""
    try:
        block = dict(spec.features) if spec.features is not None else None
        if block is None:
            default = registry.create("simulator", spec.simulator).default_feature_extractor()
            block = {"type": default}
        ext = registry.create("feature_extractor", block)
        names = [str(n) for n in ext.feature_names]
        units = getattr(ext, "feature_units", None)
        if isinstance(units, dict):
            units = [units.get(n, "") for n in names]
        config = ext.config.model_dump(mode="json") if hasattr(ext.config, "model_dump") else str(ext.config)
        version = str(getattr(ext, "version", "") or "")
        return f"{ext.name}@{version}/" + digest({"config": config, "features": names,
                                                   "units": [str(u) for u in units] if units else None})
    except Exception:  # reported by validation; a key must not fail
        return "?"


#: the entry of :func:`plugin_versions` that says how answers draw their random numbers
SEEDING_ENTRY = "answers (seeding)"
#: per-target-1: every answer a stage makes (optimiser runs, posterior draws, refinements, polish) is seeded
#: from the seed and its target's values, never from the target's position (before: no entry)
SEEDING = "per-target-1"
#: sections whose stages make (or re-use) seeded answers
SEEDING_SECTIONS: tuple[str, ...] = ("optimizers", "evaluation", "active")
#: the spec's sections only the run's bundle reads (no model depends on them): the stages that write the
#: bundle rewrite it when these change and keep their work cached (``REFRESHED_BY`` of train and invert)
BUNDLE_SECTIONS: tuple[str, ...] = ("name", "description", "pools", "default_method")


def plugin_versions(spec: Any, sections: tuple[str, ...], registry: Any) -> dict[str, str]:
    """``{path: "type@distribution==version"}`` for each plugin block in ``sections``, plus the feature
    extractor's identity (:data:`EXTRACTOR_ENTRY`) when ``sections`` hold one of :data:`EXTRACTOR_SECTIONS`,
    and the answers' seeding (:data:`SEEDING_ENTRY`) when they hold one of :data:`SEEDING_SECTIONS` (a
    stage cached under another seeding re-runs instead of serving answers this invphys would not give)."""
    out: dict[str, str] = {}
    if any(s in sections for s in EXTRACTOR_SECTIONS):
        out[EXTRACTOR_ENTRY] = extractor_identity(spec, registry)
    if any(s in sections for s in SEEDING_SECTIONS):
        out[SEEDING_ENTRY] = SEEDING
    for path, kind, block in spec.plugin_blocks():
        if path.split(".")[0] not in sections or not isinstance(block, dict):
            continue
        name = str(block.get("type"))
        try:
            info = registry.info(kind, name)
            version = f"{info.distribution}=={info.version}"
            own = getattr(info.cls, "version", None)
            if isinstance(own, str):
                version += f"/{own}"
        except Exception:  # reported by validation; a key must not fail
            version = "?"
        out[path] = f"{name}@{version}"
    return out


def without_extractor(plugins: dict[str, str]) -> dict[str, str]:
    """``plugins`` as keys hashed it before they held the extractor's identity (2026-11-28): a runner that
    also accepts markers of this older key keeps run directories made before then cached."""
    return {k: v for k, v in plugins.items() if k != EXTRACTOR_ENTRY}


def data_fingerprint(path: Path, first_ok: int | None = None) -> str:
    """The dataset's content fingerprint at ``path`` ("absent" when there is no store yet); with
    ``first_ok``, that of its first ``first_ok`` ok rows only (rows appended later leave it unchanged)."""
    from invphys.core.dataset import DatasetStore

    return DatasetStore(path).content_fingerprint(first_ok) if path.is_dir() else "absent"


def read_done(done_path: Path) -> dict[str, Any] | None:
    """A stage's ``DONE.json`` (None when absent or unreadable: the stage is then simply re-run)."""
    try:
        data = json.loads(done_path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def stale_reason(done: dict[str, Any] | None, components: dict[str, Any]) -> str:
    """Why a stage with marker ``done`` must re-run given its current key ``components``."""
    if done is None:
        return "never finished"
    before = done.get("components")
    if not isinstance(before, dict):
        return "its marker predates input tracking"
    names = {"spec": "spec sections", "plugins": "plugin versions", "data": "dataset content",
             "upstream": "an earlier stage"}
    old_plugins, plugins = before.get("plugins"), components.get("plugins")
    if isinstance(old_plugins, dict) and isinstance(plugins, dict) and old_plugins.get(EXTRACTOR_ENTRY) != \
            plugins.get(EXTRACTOR_ENTRY) and {k: v for k, v in old_plugins.items() if k != EXTRACTOR_ENTRY} == \
            {k: v for k, v in plugins.items() if k != EXTRACTOR_ENTRY}:
        names["plugins"] = ("the feature extractor (settings, units or version)" if EXTRACTOR_ENTRY in old_plugins
                            else "the key now covers the feature extractor")
    if isinstance(old_plugins, dict) and isinstance(plugins, dict) and old_plugins.get(SEEDING_ENTRY) != \
            plugins.get(SEEDING_ENTRY) and {k: v for k, v in old_plugins.items() if k != SEEDING_ENTRY} == \
            {k: v for k, v in plugins.items() if k != SEEDING_ENTRY}:
        names["plugins"] = "how answers are seeded (now per target, not by position)"
    changed = [names.get(k, k) for k in components if before.get(k) != components[k]]
    return f"{' and '.join(changed)} changed" if changed else "inputs changed"
