"""Spec problems as a reader sees them: pydantic errors turned into (path, message) pairs, each path's
YAML line, and the one message that lists them (``spec.yaml: 2 problems`` then one line each)."""

from __future__ import annotations

from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from invphys.core.errors import did_you_mean
from invphys.core.spec_model import (
    DatasetSection,
    ExperimentSpec,
    ObjectiveSection,
    ReportSection,
    TargetsSection,
    TrackerSection,
)

#: a problem: the path of the setting (keys and list indices as text) and what is wrong with it
Problem = tuple[tuple[str, ...], str]

def pydantic_problems(exc: ValidationError, prefix: tuple[str, ...],
                       known: list[str] | None = None) -> list[tuple[tuple[str, ...], str]]:
    """(path, message) of each error of ``exc`` under ``prefix``; ``known``: the field names a misspelt key
    is matched against (default: the spec section's)."""
    out = []
    suggested: set[tuple[str, ...]] = set()  # a misspelt key: its "missing" twin is not a second problem
    for err in exc.errors():
        loc = tuple(str(x) for x in err["loc"] if not str(x).startswith("function-after") and str(x) != "[key]")
        fields = known if known is not None else _section_fields(loc)
        if err["type"] == "extra_forbidden" and fields:
            match = did_you_mean(loc[-1], fields)
            if match:
                suggested.add((*loc[:-1], match.split("'")[1]))
        out.append(((*prefix, *loc), _message(err, fields), err["type"]))
    return [(path, msg) for path, msg, kind in out
            if not (kind == "missing" and path[len(prefix):] in suggested)]


def _section_fields(loc: tuple[str, ...]) -> list[str]:
    """The field names (aliases) of the spec model an error at ``loc`` (pass 1) sits in."""
    model: type[BaseModel] | None = None
    if len(loc) == 1:
        model = ExperimentSpec
    elif len(loc) == 2:
        sections: dict[str, type[BaseModel]] = {"dataset": DatasetSection, "targets": TargetsSection,
                                                 "report": ReportSection, "tracker": TrackerSection}
        model = sections.get(loc[0])
    elif len(loc) == 3 and loc[0] == "objectives":
        model = ObjectiveSection
    if model is None:
        return []
    return [f.alias or name for name, f in model.model_fields.items()]


def _message(err: Any, known: list[str] | None) -> str:
    """One error's message in the spec's words (``must be > 0``, ``unknown field. Did you mean ...``)."""
    kind, ctx = err["type"], err.get("ctx") or {}
    if kind == "greater_than":
        return f"must be > {ctx['gt']}"
    if kind == "greater_than_equal":
        return f"must be >= {ctx['ge']}"
    if kind == "less_than":
        return f"must be < {ctx['lt']}"
    if kind == "less_than_equal":
        return f"must be <= {ctx['le']}"
    if kind == "missing":
        return "required field is missing"
    if kind == "extra_forbidden":
        name = str(err["loc"][-1])
        hint = did_you_mean(name, known) if known else ""
        return f"unknown field.{hint}" if hint else "unknown field"
    if kind == "literal_error":
        return f"must be one of {ctx.get('expected', '')}"
    if kind == "value_error":
        return str(ctx.get("error", err["msg"]))
    return str(err["msg"][0].lower() + err["msg"][1:]) if err["msg"] else kind


def format_problems(source: str, problems: list[tuple[tuple[str, ...], str]],
            lines: dict[tuple[str, ...], int]) -> str:
    """One problem: one line ``source: path (line N): message``; several: a count, then one per line."""
    rows = []
    located = [(path, message, problem_line(path, lines)) for path, message in problems]
    located.sort(key=lambda item: item[2] or 0)  # in file order; file-wide problems first
    for path, message, line in located:
        where = ".".join(c if c.isprintable() else repr(c) for c in path) or "(top level)"
        rows.append(f"  {where}{f' (line {line})' if line else ''}: {message}")
    if len(rows) == 1:
        return f"{source}: {rows[0].strip()}"
    return f"{source}: {len(rows)} problems\n" + "\n".join(rows)


def problem_line(path: tuple[str, ...], lines: dict[tuple[str, ...], int]) -> int | None:
    """The YAML line of ``path`` or of its nearest enclosing key (None when unknown)."""
    for cut in range(len(path), 0, -1):
        if path[:cut] in lines:
            return lines[path[:cut]]
    return None


def line_index(node: yaml.Node | None) -> dict[tuple[str, ...], int]:
    """Map each key path of a composed YAML document to its (1-based) line."""
    index: dict[tuple[str, ...], int] = {}

    def walk(n: yaml.Node, path: tuple[str, ...]) -> None:
        if isinstance(n, yaml.MappingNode):
            for key, value in n.value:
                p = (*path, str(key.value))
                index[p] = key.start_mark.line + 1
                walk(value, p)
        elif isinstance(n, yaml.SequenceNode):
            for i, item in enumerate(n.value):
                p = (*path, str(i))
                index[p] = item.start_mark.line + 1
                walk(item, p)

    if node is not None:
        walk(node, ())
    return index
