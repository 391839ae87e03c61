"""The one safe way invphys reads YAML (and the text files it comes in).

:func:`read_text` refuses what is not a regular file (``/dev/zero``, a FIFO, a directory), files larger
than :data:`MAX_BYTES`, text that is not UTF-8 and text with NUL bytes. :func:`load` parses with
PyYAML's safe loader and then refuses, before building any Python object:

* more than one document, nesting deeper than :data:`MAX_DEPTH`;
* aliases that expand to more than :data:`MAX_NODES` nodes (the "billion laughs" bomb) or refer to
  themselves;
* a key given twice in one mapping (naming both lines; YAML would silently keep the last).

Every refusal is an :class:`~invphys.core.errors.InvphysError` (by default a
:class:`~invphys.core.errors.SpecError`) whose message starts with the source name::

    data, node = load(read_text("spec.yaml"), source="spec.yaml")
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

from invphys.core.errors import InvphysError, SpecError

#: largest YAML file read (bytes); the environment variable ``INVPHYS_MAX_SPEC_BYTES`` overrides it
MAX_BYTES = 1 << 20
#: deepest nesting of mappings and sequences
MAX_DEPTH = 40
#: most nodes a document may expand to, aliases expanded
MAX_NODES = 100_000


def max_bytes() -> int:
    """The size limit in force (:data:`MAX_BYTES` or ``INVPHYS_MAX_SPEC_BYTES``)."""
    try:
        return int(os.environ.get("INVPHYS_MAX_SPEC_BYTES", MAX_BYTES))
    except ValueError:
        return MAX_BYTES


def read_text(path: str | os.PathLike[str], what: str = "spec", error: type[InvphysError] = SpecError,
              limit: int | None = None) -> str:
    """The UTF-8 text of the regular file ``path`` (at most ``limit`` bytes), or ``error`` saying why not."""
    p = Path(path)
    limit = max_bytes() if limit is None else limit
    try:
        st = os.stat(p)
    except OSError as exc:
        raise error(f"cannot read {what} {str(p)!r}: {exc.strerror or exc}") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"cannot read {what} {str(p)!r}: it is a directory, not a file")
    if not stat.S_ISREG(st.st_mode):
        raise error(f"cannot read {what} {str(p)!r}: not a regular file (a device, pipe or socket)")
    if st.st_size > limit:
        raise error(f"{what} {str(p)!r} is {st.st_size:,} bytes, over the {limit:,}-byte limit")
    try:
        with open(p, "rb") as fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise error(f"cannot read {what} {str(p)!r}: {exc.strerror or exc}") from None
    if len(data) > limit:
        raise error(f"{what} {str(p)!r} is over the {limit:,}-byte limit")
    return decode(data, f"{what} {str(p)!r}", error)


def decode(data: bytes, source: str, error: type[InvphysError] = SpecError) -> str:
    """``data`` as UTF-8 text (a leading BOM dropped), refusing binary content with its line."""
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    nul = data.find(b"\x00")
    if nul >= 0:
        line = data.count(b"\n", 0, nul) + 1
        raise error(f"{source}: not a text file (a NUL byte on line {line})")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise error(f"{source}: not UTF-8 text (byte 0x{data[exc.start]:02x} on line {line})") from None


def load(text: str, source: str = "<yaml>", error: type[InvphysError] = SpecError) -> tuple[Any, yaml.Node | None]:
    """Parse one YAML document safely: returns ``(data, node)`` (``node`` for line numbers)."""
    if len(text) > max_bytes():
        raise error(f"{source}: {len(text):,} characters, over the {max_bytes():,}-byte limit")
    loader: yaml.SafeLoader | None = None
    try:
        loader = yaml.SafeLoader(text)
        node = loader.get_single_node()
        if node is None:
            return None, None
        check_node(node, source, error)
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


def check_node(root: yaml.Node, source: str, error: type[InvphysError] = SpecError) -> None:
    """Refuse deep nesting, self-referring or exploding aliases and duplicate keys (see module doc)."""
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
        if isinstance(node, yaml.MappingNode):
            seen: dict[str, int] = {}
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value != "<<":
                    line = k.start_mark.line + 1
                    if k.value in seen:
                        raise error(f"{source}: key {k.value!r} appears twice in one mapping (lines "
                                    f"{seen[k.value]} and {line})")
                    seen[k.value] = line
                total += size(k, depth + 1) + size(v, depth + 1)
                if total > MAX_NODES:
                    break
        elif isinstance(node, yaml.SequenceNode):
            for item in node.value:
                total += size(item, depth + 1)
                if total > MAX_NODES:
                    break
        active.discard(key)
        if total > MAX_NODES:
            raise error(f"{source}: expands to more than {MAX_NODES:,} values (aliases expanded): "
                        "too large for a spec")
        sizes[key] = total
        return total

    size(root, 0)
