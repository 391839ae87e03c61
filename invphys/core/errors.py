"""Exceptions users meet, and the did-you-mean helper used by every name lookup.

Every error that is the user's to fix derives from :class:`InvphysError`; the CLI prints its message
without a traceback and exits with status 2.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class InvphysError(Exception):
    """Base class of errors caused by input the user can correct (exit status 2 in the CLI)."""


class PluginNotFoundError(InvphysError, LookupError):
    """No plugin of the requested kind has the requested name."""


class PluginLoadError(InvphysError, ImportError):
    """A plugin (or its distribution's entry point) failed to import or register."""


class DuplicatePluginError(InvphysError):
    """Two distributions register a plugin of the same kind under the same name."""


class SpecError(InvphysError, ValueError):
    """An experiment spec is malformed; the message lists each problem with its path (and line).

    :attr:`problems` holds them as ``(path, message)`` pairs (path a tuple of keys; empty when the file
    itself could not be read or parsed) and :attr:`lines` each path's YAML line, where known.
    """

    def __init__(self, message: str, problems: list[tuple[tuple[str, ...], str]] | None = None,
                 lines: dict[tuple[str, ...], int] | None = None) -> None:
        super().__init__(message)
        self.problems = list(problems or [])
        self.lines = dict(lines or {})


class ParameterRangeError(InvphysError, ValueError):
    """A parameter is unknown, missing, or outside its physical range."""


class DeviceUnavailableError(InvphysError, RuntimeError):
    """A compute device (e.g. CUDA) was asked for where there is none."""


class Interrupted(KeyboardInterrupt):
    """A stop by signal after the work done so far was kept (Ctrl-C: ``interrupted``, exit 130; SIGTERM:
    ``terminated``, exit 143). A :class:`KeyboardInterrupt`, so nothing catches it as an ordinary error."""

    def __init__(self, word: str = "interrupted", exit_code: int = 130) -> None:
        super().__init__(word)
        self.word = word
        self.exit_code = exit_code


class SimulationFailed(RuntimeError):
    """A simulation blew up (NaN, particles leaving the domain, energy blow-up).

    Executors catch this and record a failed row carrying :attr:`reason`; it is not a user error.
    """

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def did_you_mean(name: str, candidates: Iterable[str]) -> str:
    """``" Did you mean 'x'?"`` for the closest candidate, or ``""`` when nothing is close."""
    matches = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.6)
    if not matches:
        lowered = {c.replace("_", "").replace("-", "").lower(): c for c in candidates}
        key = name.replace("_", "").replace("-", "").lower()
        if key in lowered:
            matches = [lowered[key]]
    return f" Did you mean {matches[0]!r}?" if matches else ""
