"""Pass 3 of the spec validation: what can be known without training, so that ``validate`` refuses what
``run`` would (features the objectives name, policies, the dataset and its extra stores, the targets)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel

from invphys.core.errors import InvphysError, did_you_mean
from invphys.core.spec_lookup import PluginLookup, plugin_lookup
from invphys.core.spec_model import ExperimentSpec, ExtraStore


def validate_references(spec: ExperimentSpec, registry: PluginLookup | None = None) -> list[tuple[tuple[str, ...], str]]:
    """Pass 3: what can be known without training, so that ``validate`` refuses what ``run`` would.

    Objective weights name features of the extractor; a ``warm_start`` names a goal-conditioned entry
    (or an existing ``policy_path``); ``dataset.path`` is a dataset (or ``if_missing: generate``); an
    explicit ``targets.n`` fits in the held-out split.
    """
    reg = plugin_lookup(registry)
    problems: list[tuple[tuple[str, ...], str]] = []
    if spec.objectives:
        names = _feature_names(spec, reg)
        if names is not None:
            for label, section in spec.objectives.items():
                for feature in section.weights:
                    if feature not in names:
                        problems.append((("objectives", label, "weights", feature),
                                         f"no feature {feature!r}.{did_you_mean(feature, names)} "
                                         f"Features: {', '.join(names)}"))
    classes: dict[str, Any] = {}
    for label, block in spec.optimizers.items():
        try:
            classes[label] = reg.get("optimizer", str(block["type"]))
        except Exception:  # reported by pass 2
            continue
    goal_conditioned = [k for k, c in classes.items() if getattr(c, "goal_conditioned", False)]
    for label, cls in classes.items():
        if "policy" not in getattr(cls, "Config", BaseModel).model_fields:
            continue
        block = spec.optimizers[label]
        policy, policy_path = block.get("policy"), block.get("policy_path")
        if policy is not None and policy not in goal_conditioned:
            problems.append((("optimizers", label, "policy"),
                             f"{policy!r} is not a goal-conditioned entry"
                             f"{did_you_mean(str(policy), goal_conditioned)} (goal-conditioned entries: "
                             f"{', '.join(goal_conditioned) or 'none'})"))
        elif policy is None and policy_path is None:
            problems.append((("optimizers", label), "needs `policy: <label of a goal-conditioned entry>`"))
        elif policy is None and not Path(str(policy_path)).is_dir():
            problems.append((("optimizers", label, "policy_path"), f"no saved policy at {policy_path!r}"))
    problems += _dataset_problems(spec)
    problems += _target_problems(spec, reg)
    return problems


def _target_problems(spec: ExperimentSpec, reg: Any) -> list[tuple[tuple[str, ...], str]]:
    """``targets.values`` / ``targets.file``: read and checked against the extractor's feature names as the
    invert stage will (a file that is missing, unreadable or names an unknown feature is refused now)."""
    from invphys.core.user_targets import from_mappings, read_target_file, require_exact

    tg = spec.targets
    if tg.values is None and tg.file is None:
        return []
    names = _feature_names(spec, reg)
    where = ("targets", "values") if tg.values is not None else ("targets", "file")
    try:
        if tg.file is not None:
            p = Path(tg.file)
            if not p.is_file():
                kind = "a directory" if p.is_dir() else "not a regular file" if p.exists() else "absent"
                return [(where, f"{tg.file!r} is {kind}: name a JSON, YAML or CSV file of targets")]
            if names is not None:
                require_exact(read_target_file(p, names), "targets.file")
            else:  # the features cannot be known without running: at least the file must be readable
                with p.open("rb"):
                    pass
        elif names is not None:
            require_exact(from_mappings(tg.values or [], names, source="targets.values"), "targets.values")
    except InvphysError as exc:
        return [(where, str(exc).removeprefix("targets.values: "))]
    except OSError as exc:
        return [(where, f"cannot read {tg.file!r}: {exc.strerror or exc}")]
    return []


def _feature_names(spec: ExperimentSpec, reg: Any) -> list[str] | None:
    """The extractor's feature names, or None when they cannot be known without running anything."""
    try:
        block = spec.features
        if block is None:
            default = reg.create("simulator", spec.simulator).default_feature_extractor()
            if default is None:
                return None
            block = {"type": default}
        return [str(n) for n in reg.create("feature_extractor", block).feature_names]
    except Exception:  # e.g. an extractor that needs a device: the run will say
        return None


def _dataset_problems(spec: ExperimentSpec) -> list[tuple[tuple[str, ...], str]]:
    """``dataset.path`` (a store, or absent with ``if_missing: generate``), ``extra_train``, and ``targets.n``
    against the held-out split."""
    ds = spec.dataset
    problems: list[tuple[tuple[str, ...], str]] = []
    rows: int | None = ds.n
    if ds.path is not None:
        p = Path(ds.path)
        if p.exists() and not p.is_dir():
            return [(("dataset", "path"), f"{ds.path!r} is a file, not a dataset directory")]
        if p.is_dir() and (p / "_metadata.json").is_file():
            broken = _store_problem(p)
            if broken:
                return [(("dataset", "path"), broken)]
            rows = _stored_ok_rows(p)
        elif p.is_dir() and any(not c.name.startswith(".") for c in p.iterdir()):
            return [(("dataset", "path"), f"{ds.path!r} is not an invphys dataset (no _metadata.json)")]
        elif not p.exists() and ds.if_missing == "error":
            return [(("dataset", "path"), f"no dataset at {ds.path!r} (set `if_missing: generate` to create it)")]
    if ds.extra_train:
        problems += _extra_store_problems(ds.path, ds.extra_train)
    stages = spec.stages or []
    tg = spec.targets
    explicit = "n" in tg.model_fields_set and getattr(tg, "values", None) is None and getattr(tg, "file", None) is None
    if "invert" in stages and explicit and rows is not None:
        held_out = max(1, round(rows * ds.test_fraction))
        if tg.n > held_out:
            problems.append((("targets", "n"), f"{tg.n} targets, but the held-out split has at most {held_out} "
                             f"rows ({rows} rows x test_fraction {ds.test_fraction:g})"))
    if "validate_n" in tg.model_fields_set and "n" in tg.model_fields_set and tg.validate_n > tg.n:
        problems.append((("targets", "validate"), f"{tg.validate_n} targets to validate, but targets.n is {tg.n}"))
    return problems



def _extra_store_problems(primary: str | None, extras: list[ExtraStore]) -> list[tuple[tuple[str, ...], str]]:
    """``dataset.extra_train``: each store readable, of the primary store's problem, and holding at
    least the ok rows its ``rows`` asks for."""
    from invphys.core.dataset import DatasetStore
    from invphys.core.dataset_union import check_extra_stores

    for i, extra in enumerate(extras):
        path = Path(extra.path)
        broken = _store_problem(path) if path.is_dir() else f"no dataset at {extra.path!r}"
        if broken:
            return [(("dataset", "extra_train", str(i)), broken)]
    if primary is None or not (Path(primary) / "_metadata.json").is_file():
        return [(("dataset", "extra_train"), "needs dataset.path: an existing primary store to join")]
    try:
        check_extra_stores(Path(primary), [e.path for e in extras])
    except InvphysError as exc:
        return [(("dataset", "extra_train"), str(exc).removeprefix("dataset.extra_train: "))]
    problems: list[tuple[tuple[str, ...], str]] = []
    for i, extra in enumerate(extras):
        if extra.rows is not None:
            held = DatasetStore(extra.path).ok_count()
            if held < extra.rows:
                problems.append((("dataset", "extra_train", str(i), "rows"),
                                 f"{extra.path!r} holds {held} ok rows, fewer than rows: {extra.rows}"))
    return problems


def _store_problem(path: Path) -> str | None:
    """Why the store at ``path`` cannot be read (None when it can): the check every reader makes."""
    from invphys.core.dataset import DatasetStore

    try:
        DatasetStore(path).keys()
    except InvphysError as exc:
        return str(exc)
    return None


def _stored_ok_rows(path: Path) -> int | None:
    """The ok-row count a store's metadata records (None when it does not say)."""
    try:
        import json

        totals = json.loads((path / "_metadata.json").read_text()).get("totals", {})
        ok = totals.get("ok") if isinstance(totals, dict) else None
        return int(ok) if isinstance(ok, int) and ok >= 0 else None
    except (OSError, ValueError, AttributeError):
        return None
