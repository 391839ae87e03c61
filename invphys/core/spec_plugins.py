"""Pass 2 of the spec validation: each plugin block checked by its plugin's ``Config``, and the spec's JSON
Schema with a branch per installed plugin.

Plugins are looked up through :func:`invphys.core.spec_lookup.plugin_lookup` (the process's registry, or the
one a caller passes): core imports nothing of the registry.
"""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

from invphys.core.errors import InvphysError
from invphys.core.spec_lookup import PluginLookup, plugin_lookup
from invphys.core.spec_model import ExperimentSpec
from invphys.core.spec_problems import pydantic_problems


def validate_plugin_blocks(spec: ExperimentSpec | list[tuple[str, str, Any]],
                           registry: PluginLookup | None = None) -> list[tuple[tuple[str, ...], str]]:
    """Pass 2: each plugin block by its plugin's Config (a spec's blocks, or a list of (path, kind, block)).
    Returns (path, message) problems."""
    reg = plugin_lookup(registry)
    problems: list[tuple[tuple[str, ...], str]] = []
    blocks = spec if isinstance(spec, list) else [*spec.plugin_blocks(), *spec.evaluation_blocks()]
    for dotted, kind, block in blocks:
        path = tuple(dotted.split("."))
        if not isinstance(block, dict) or "type" not in block:
            problems.append((path, "needs a 'type' field naming the plugin"))
            continue
        try:
            cls = reg.get(kind, str(block["type"]))
        except InvphysError as exc:
            problems.append(((*path, "type"), str(exc)))
            continue
        settings = {k: v for k, v in block.items() if k != "type"}
        try:
            cls.Config.model_validate(settings)
        except ValidationError as exc:
            problems += pydantic_problems(exc, path, known=list(cls.Config.model_fields))
    return problems



#: the JSON Schema dialect and identifier of ``invphys schema``
SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"
SCHEMA_ID = "urn:invphys:experiment-spec:1"
#: a ``type: package.module:Class`` plugin name (unpackaged code), as the registry accepts it
MODULE_CLASS_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$"


def _module_class_block(kind: str) -> dict[str, Any]:
    """The schema branch of a plugin named by ``module:Class``: its settings are checked by ``validate``."""
    return {"title": f"{kind}:module:Class", "type": "object", "required": ["type"],
            "properties": {"type": {"type": "string", "pattern": MODULE_CLASS_PATTERN}},
            "additionalProperties": True,
            "description": "a plugin named by its import path; `invphys validate` checks its settings"}


def json_schema(registry: PluginLookup | None = None) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of the spec, with each plugin block as a ``oneOf`` over the installed
    plugins' Configs and a ``module:Class`` branch for unpackaged plugins."""
    reg = plugin_lookup(registry)
    schema = {"$schema": SCHEMA_DIALECT, "$id": SCHEMA_ID, **ExperimentSpec.model_json_schema(by_alias=True)}
    defs = schema.setdefault("$defs", {})
    per_kind: dict[str, list[dict[str, Any]]] = {}
    for info in reg.infos():
        sub = info.cls.Config.model_json_schema()
        for k, v in sub.pop("$defs", {}).items():
            defs.setdefault(k, v)
        props = dict(sub.get("properties", {}))
        extra_keys = {"space": {"type": "string"}, "evaluator": {"enum": ["shared", "own_head"]},
                      "uncertainty_penalty": {"type": "number", "minimum": 0}} \
            if info.kind == "optimizer" else {}
        sub["properties"] = {"type": {"const": info.name}, **props, **extra_keys}
        sub["required"] = ["type", *sub.get("required", [])]
        sub["additionalProperties"] = False
        sub["title"] = f"{info.kind}:{info.name}"
        sub["description"] = (info.cls.__doc__ or "").strip().split("\n")[0]
        per_kind.setdefault(info.kind, []).append(sub)
    for kind, subs in per_kind.items():
        defs[f"{kind}_block"] = {"oneOf": [*subs, _module_class_block(kind)]}
    props = schema["properties"]
    single = {"simulator": "simulator", "features": "feature_extractor", "executor": "executor",
              "surrogate": "surrogate", "validator": "validator"}
    for section, kind in single.items():
        if kind in per_kind:
            ref = {"$ref": f"#/$defs/{kind}_block"}
            props[section] = {"anyOf": [ref, {"type": "null"}]} if section in ("features", "surrogate", "validator") else ref
    for section, kind in (("latent_models", "latent_model"), ("optimizers", "optimizer")):
        if kind in per_kind:
            props[section] = {"type": "object", "additionalProperties": {"$ref": f"#/$defs/{kind}_block"}}
    return schema
