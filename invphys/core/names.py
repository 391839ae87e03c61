"""The one rule for names that become file or directory names (spec labels, run names).

A safe name is 1 to :data:`MAX_NAME_CHARS` characters of ASCII letters, digits, ``_`` and ``-``, starting
with a letter or digit, and not a name Windows reserves (``con``, ``nul``, ``com1``, ...). It can never
hold ``/``, ``\\``, ``..``, a leading ``-`` (read as an option) or a leading ``.`` (hidden), so joining it
to a directory never leaves that directory::

    >>> check_name("cma-raw")
    'cma-raw'
    >>> check_name("../x")
    Traceback (most recent call last):
    ...
    ValueError: '../x' is not a safe name: use 1-64 letters, digits, '_' or '-', starting with a letter or digit
"""

from __future__ import annotations

import re
from pathlib import Path

MAX_NAME_CHARS = 64
NAME_PATTERN = rf"^[A-Za-z0-9][A-Za-z0-9_-]{{0,{MAX_NAME_CHARS - 1}}}$"
_NAME_RE = re.compile(NAME_PATTERN)
_RESERVED = re.compile(r"^(con|prn|aux|nul|com[0-9]|lpt[0-9])$", re.IGNORECASE)
RULE = f"use 1-{MAX_NAME_CHARS} letters, digits, '_' or '-', starting with a letter or digit"


def is_safe_name(name: object) -> bool:
    """True when ``name`` is a string that :func:`check_name` accepts."""
    return isinstance(name, str) and bool(_NAME_RE.match(name)) and not _RESERVED.match(name)


def check_name(name: object) -> str:
    """Return ``name`` if it is safe as a single path component, else raise ``ValueError`` saying why."""
    if not isinstance(name, str):
        raise ValueError(f"{name!r} is not a safe name: must be a string")
    shown = name if len(name) <= 80 else name[:77] + "..."
    if len(name) > MAX_NAME_CHARS:
        raise ValueError(f"{shown!r} is not a safe name: longer than {MAX_NAME_CHARS} characters")
    if _RESERVED.match(name):
        raise ValueError(f"{shown!r} is not a safe name: reserved as a device name on Windows")
    if not _NAME_RE.match(name):
        raise ValueError(f"{shown!r} is not a safe name: {RULE}")
    return name


def safe_child(directory: str | Path, name: str) -> Path:
    """``directory / name`` after :func:`check_name` (the one way to turn a label into a path)."""
    return Path(directory) / check_name(name)
