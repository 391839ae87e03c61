"""The one safe way invphys parses YAML: specs, and (through :mod:`invphys.core.safe_read`) every
YAML file a user or a shared artifact hands it.

:func:`read_text` reads a spec through the bounded reader :func:`invphys.core.bounded_read.read_user_text`
(regular files only: not ``/dev/zero``, a FIFO, a directory; at most :data:`MAX_BYTES`; UTF-8 without
NUL bytes, a BOM dropped). :func:`load` parses with PyYAML's safe loader and then refuses, before
building any Python object:

* more than one document, nesting deeper than :data:`MAX_DEPTH`;
* aliases that expand to more than :data:`MAX_NODES` nodes (the "billion laughs" bomb) or refer to
  themselves;
* a key given twice in one mapping (naming both lines; YAML would silently keep the last);
* an integer too large for a float (more than about 1e308), naming its line.

Every refusal is an :class:`~invphys.core.errors.InvphysError` (by default a
:class:`~invphys.core.errors.SpecError`) whose message starts with the source name::

    data, node = load(read_text("spec.yaml"), source="spec.yaml")
"""

from __future__ import annotations

import os
from typing import Any

import yaml

from invphys.core.errors import InvphysError, SpecError

#: largest YAML file read (bytes); the environment variable ``INVPHYS_MAX_SPEC_BYTES`` overrides it
MAX_BYTES = 1 << 20
#: deepest nesting of mappings and sequences
MAX_DEPTH = 40
#: most nodes a document may expand to, aliases expanded
MAX_NODES = 100_000
#: most digits of an integer (a float holds at most ~1e308)
MAX_INT_DIGITS = 330
INT_TAG = "tag:yaml.org,2002:int"


def max_bytes() -> int:
    """The size limit in force (:data:`MAX_BYTES` or ``INVPHYS_MAX_SPEC_BYTES``)."""
    try:
        return int(os.environ.get("INVPHYS_MAX_SPEC_BYTES", MAX_BYTES))
    except ValueError:
        return MAX_BYTES


def read_text(path: str | os.PathLike[str], what: str = "spec", error: type[InvphysError] = SpecError,
              limit: int | None = None) -> str:
    """The UTF-8 text of the regular file ``path`` (at most ``limit`` bytes), or ``error`` saying why not
    (:func:`invphys.core.bounded_read.read_user_text`: the one bounded reader)."""
    from invphys.core.bounded_read import UserFileError, read_user_text

    try:
        return read_user_text(path, what=what, max_bytes=max_bytes() if limit is None else limit)
    except UserFileError as exc:
        raise error(str(exc)) from None


def decode(data: bytes, source: str, error: type[InvphysError] = SpecError) -> str:
    """``data`` as UTF-8 text (a leading BOM dropped), refusing binary content with its line."""
    from invphys.core.bounded_read import text_of

    try:
        return text_of(data)
    except InvphysError as exc:
        raise error(f"{source}: {exc}") from None


def load(text: str, source: str = "<yaml>", error: type[InvphysError] = SpecError, limit: int | None = None,
         max_nodes: int = MAX_NODES, fast: bool = False) -> tuple[Any, yaml.Node | None]:
    """Parse one YAML document safely: returns ``(data, node)`` (``node`` for line numbers).

    ``limit`` (characters; default: the spec limit, :func:`max_bytes`) and ``max_nodes`` bound the text
    and the values it expands to; data files (targets, manifests) pass their own, and ``fast``: LibYAML's
    parser where PyYAML has it (about 4x faster on large files; the same checks follow)."""
    limit = max_bytes() if limit is None else limit
    if len(text) > limit:
        raise error(f"{source}: {len(text):,} characters, over the {limit:,}-byte limit")
    loader: Any = None
    try:
        loader = yaml.CSafeLoader(text) if fast and getattr(yaml, "__with_libyaml__", False) else yaml.SafeLoader(text)
        node = loader.get_single_node()
        if node is None:
            return None, None
        check_node(node, source, error, max_nodes)
        return loader.construct_document(node), node
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        parts = [getattr(exc, "context", None), getattr(exc, "problem", None)]
        problem = "; ".join(p for p in parts if p) or str(exc).splitlines()[0]
        raise error(f"{source}: not valid YAML{where}: {problem}") from None
    except RecursionError:
        raise error(f"{source}: nested too deeply (more than {MAX_DEPTH} levels)") from None
    finally:
        if loader is not None:
            loader.dispose()


def check_node(root: yaml.Node, source: str, error: type[InvphysError] = SpecError,
               max_nodes: int = MAX_NODES) -> None:
    """Refuse deep nesting, self-referring or exploding aliases, duplicate keys and integers too large
    for a float (see module doc)."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(node: yaml.Node, depth: int) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in active:
            raise error(f"{source}: an alias refers to the node that contains it (line {node.start_mark.line + 1})")
        if depth > MAX_DEPTH:
            raise error(f"{source}: nested too deeply (more than {MAX_DEPTH} levels, line "
                        f"{node.start_mark.line + 1})")
        total = 1
        active.add(key)
        if isinstance(node, yaml.ScalarNode) and node.tag == INT_TAG:
            check_int(node, source, error)
        elif isinstance(node, yaml.MappingNode):
            seen: dict[str, int] = {}
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value != "<<":
                    line = k.start_mark.line + 1
                    if k.value in seen:
                        raise error(f"{source}: key {k.value!r} appears twice in one mapping (lines "
                                    f"{seen[k.value]} and {line})")
                    seen[k.value] = line
                total += size(k, depth + 1) + size(v, depth + 1)
                if total > max_nodes:
                    break
        elif isinstance(node, yaml.SequenceNode):
            for item in node.value:
                total += size(item, depth + 1)
                if total > max_nodes:
                    break
        active.discard(key)
        if total > max_nodes:
            raise error(f"{source}: expands to more than {max_nodes:,} values (aliases expanded): too large")
        sizes[key] = total
        return total

    size(root, 0)


def check_int(node: yaml.ScalarNode, source: str, error: type[InvphysError] = SpecError) -> None:
    """Refuse an integer a float cannot hold (more than about 1e308), naming its line."""
    import sys

    if len(node.value) <= 20:  # well within a float (a sexagesimal 1:2:3 or 0x.. of this length too)
        return
    digits = sum(c.isalnum() for c in node.value)
    try:
        value = None if digits > MAX_INT_DIGITS else yaml.constructor.SafeConstructor().construct_yaml_int(node)
    except ValueError:
        value = None
    if value is None or abs(value) > sys.float_info.max:
        text = node.value if len(node.value) <= 16 else node.value[:12] + "..."
        raise error(f"{source}: the integer {text} on line {node.start_mark.line + 1} is too large for a number "
                    "(at most ~1e308)")
