"""Loading a spec: read the YAML safely, then every check at once (values, shape, plugin blocks,
cross-references), each problem with its path and YAML line (:class:`~invphys.core.errors.SpecError`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from invphys.core import safe_yaml
from invphys.core.errors import SpecError
from invphys.core.spec_lookup import PluginLookup
from invphys.core.spec_model import ExperimentSpec, optimizer_plugin_block
from invphys.core.spec_plugins import validate_plugin_blocks
from invphys.core.spec_problems import format_problems, line_index, pydantic_problems
from invphys.core.spec_references import validate_references


def load_spec(path: str | Path, registry: PluginLookup | None = None) -> ExperimentSpec:
    """Read, parse and fully validate a YAML spec file. Raises :class:`SpecError`.

    The file must be a regular UTF-8 file within the size limit of :mod:`invphys.core.safe_yaml`.
    """
    p = Path(path)
    text = safe_yaml.read_text(p, what="spec")
    return parse_spec(text, source=str(p), registry=registry)


def parse_spec(text: str, source: str = "<spec>", registry: PluginLookup | None = None) -> ExperimentSpec:
    """Parse YAML text safely (:func:`invphys.core.safe_yaml.load`) and validate it (every pass)."""
    data, node = safe_yaml.load(text, source=source)
    if not isinstance(data, dict):
        raise SpecError(f"{source}: a spec is a YAML mapping with at least 'name' and 'simulator'")
    lines = line_index(node)
    return validate_spec(data, source=source, lines=lines, registry=registry)


def validate_spec(data: dict[str, Any], source: str = "<spec>", lines: dict[tuple[str, ...], int] | None = None,
                  registry: PluginLookup | None = None, references: bool = True) -> ExperimentSpec:
    """Validate an already-parsed spec mapping: values (keys are strings, numbers finite), shape,
    plugin blocks, and (``references``) the cross-references :func:`validate_references` checks."""
    lines = lines or {}
    problems = spec_problems(data, registry, references)
    if problems:
        raise SpecError(format_problems(source, problems, lines), problems=problems, lines=lines)
    return ExperimentSpec.model_validate(data)


def spec_problems(data: dict[str, Any], registry: PluginLookup | None = None,
                  references: bool = True) -> list[tuple[tuple[str, ...], str]]:
    """Every problem of a parsed spec at once, as (path, message): values, shape, plugin blocks, and
    (``references``) the cross-references. A section that fails the shape check still has its plugin
    blocks checked; the cross-references need a spec whose shape is right."""
    problems = value_problems(data)
    try:  # keys that are not text are reported once, above; the shape check sees the rest
        spec: ExperimentSpec | None = ExperimentSpec.model_validate(_text_keys(data) if problems else data)
    except ValidationError as exc:
        spec = None
        problems += [(path, msg) for path, msg in pydantic_problems(exc, ())
                     if not any(path[:len(q)] == q for q, _ in problems)]
    blocks = [*spec.plugin_blocks(), *spec.evaluation_blocks()] if spec is not None else _raw_plugin_blocks(data)
    plugin_problems = validate_plugin_blocks(blocks, registry)
    problems += [(path, msg) for path, msg in plugin_problems
                 if not any(path[:len(q)] == q or q[:len(path)] == path for q, _ in problems)]
    if spec is not None and references:  # each check copes with a block that failed above
        problems += [(path, msg) for path, msg in validate_references(spec, registry)
                     if not any(path[:len(q)] == q or q[:len(path)] == path for q, _ in problems)]
    return problems


def _text_keys(data: Any) -> Any:
    """``data`` without the mapping entries whose key is not text (at any depth)."""
    if isinstance(data, dict):
        return {k: _text_keys(v) for k, v in data.items() if isinstance(k, str)}
    if isinstance(data, list):
        return [_text_keys(v) for v in data]
    return data


def _raw_plugin_blocks(data: dict[str, Any]) -> list[tuple[str, str, Any]]:
    """The plugin blocks of a spec mapping whose shape failed, as :meth:`ExperimentSpec.plugin_blocks`
    gives them (what is not a mapping of blocks is left to the shape check's problems)."""
    def mapping(value: Any) -> dict[str, Any]:
        return value if isinstance(value, dict) else {}

    blocks: list[tuple[str, str, Any]] = []
    for section, kind in (("simulator", "simulator"), ("executor", "executor"), ("features", "feature_extractor"),
                          ("surrogate", "surrogate"), ("validator", "validator")):
        if isinstance(data.get(section), dict):
            blocks.append((section, kind, data[section]))
    blocks += [(f"latent_models.{k}", "latent_model", b) for k, b in mapping(data.get("latent_models")).items()
               if isinstance(b, dict)]
    blocks += [(f"optimizers.{k}", "optimizer", optimizer_plugin_block(b))
               for k, b in mapping(data.get("optimizers")).items() if isinstance(b, dict)]
    baselines = mapping(mapping(data.get("evaluation")).get("baselines"))
    blocks += [(f"evaluation.baselines.{k}", "optimizer", b) for k, b in baselines.items() if isinstance(b, dict)]
    return blocks


def value_problems(data: Any, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], str]]:
    """The one finite-number rule (and string keys): every float anywhere in a spec must be finite.

    YAML reads ``.inf`` and ``.nan`` as floats; no spec setting means anything by them, so they are
    refused wherever they appear, with their path.
    """
    problems: list[tuple[tuple[str, ...], str]] = []
    if isinstance(data, float) and not math.isfinite(data):
        problems.append((path, f"must be a finite number, not {data}"))
    elif isinstance(data, dict):
        for key, value in data.items():
            if not isinstance(key, str):
                problems.append(((*path, str(key)), f"the key {key!r} is not text; quote it"))
                continue
            problems += value_problems(value, (*path, key))
    elif isinstance(data, list):
        for i, item in enumerate(data):
            problems += value_problems(item, (*path, str(i)))
    return problems
