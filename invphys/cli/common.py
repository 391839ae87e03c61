"""Helpers shared by CLI commands: error handling (exit 2 on bad input) and ``--json`` output."""

from __future__ import annotations

import errno
import functools
import json
import logging
import os
import sys
from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

import typer
from rich.console import Console

from invphys.core.errors import InvphysError

F = TypeVar("F", bound=Callable[..., Any])

#: piped output is never cut to 80 columns: tables keep full plugin and class names
PIPED_WIDTH = 200


def _console(stderr: bool) -> Console:
    stream = sys.stderr if stderr else sys.stdout
    return Console(stderr=stderr, width=None if stream.isatty() else PIPED_WIDTH)


#: human-readable output (tables, progress) goes to stderr so that stdout stays machine-readable
console = _console(stderr=True)
out_console = _console(stderr=False)

_state: dict[str, Any] = {"debug": False, "level": logging.INFO}


def set_debug(value: bool) -> None:
    """``--debug``: tracebacks instead of short errors, and the heavy back-ends' own log lines."""
    if value:
        os.environ["INVPHYS_DEBUG"] = "1"
    elif _state["debug"]:  # set by an earlier --debug in this process (tests): not inherited further
        os.environ.pop("INVPHYS_DEBUG", None)
    _state["debug"] = value


def debug_enabled() -> bool:
    return bool(_state["debug"])


def log_level() -> int:
    """The level ``-v``/``-q`` set: INFO by default, WARNING with ``-q``, ERROR with ``-qq``."""
    return int(_state["level"])


def quiet() -> bool:
    """``-q`` or more: no stage lines, no progress bars, no INFO lines of invphys or its back-ends."""
    return log_level() >= logging.WARNING


def silent() -> bool:
    """``-qq``: nothing but errors on stderr, and no status-only lines (``finished``, ``valid``) on stdout."""
    return log_level() >= logging.ERROR


def configure_logging(verbose: int = 0, quiet: int = 0) -> int:
    """Send the ``invphys`` loggers to stderr; returns the level set.

    Default INFO (what each stage did); ``-v`` DEBUG; ``-q`` WARNING; ``-qq`` ERROR. Library use
    (no CLI) keeps Python's defaults: only warnings and errors surface unless the caller configures.
    """
    level = {-2: logging.ERROR, -1: logging.WARNING, 0: logging.INFO}.get(max(verbose - quiet, -2), logging.DEBUG)
    logger = logging.getLogger("invphys")
    for handler in [h for h in logger.handlers if isinstance(h, _ConsoleHandler)]:
        logger.removeHandler(handler)
    handler = _ConsoleHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s" if level < logging.INFO
                                           else "%(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    _state["level"] = level
    return level


class _ConsoleHandler(logging.Handler):
    """Log records as plain lines on the stderr console (warnings in yellow, errors in red)."""

    STYLES: ClassVar[dict[int, str]] = {logging.WARNING: "yellow", logging.ERROR: "bold red"}

    def emit(self, record: logging.LogRecord) -> None:
        try:
            style = self.STYLES.get(min(record.levelno, logging.ERROR) if record.levelno >= logging.WARNING else 0)
            console.print(self.format(record), style=style, markup=False, highlight=False, soft_wrap=True)
        except Exception:
            self.handleError(record)


#: exit status of a user error (bad spec, unknown plugin, out-of-range value, corrupt input)
EXIT_USER_ERROR = 2
#: exit status of a bug: an exception nobody meant a user to see
EXIT_INTERNAL_ERROR = 1
#: exit status after Ctrl-C (128 + SIGINT), with the line ``interrupted`` on stderr
EXIT_INTERRUPTED = 130
#: operating-system errors that are the user's environment, not a bug: exit 2 with one line
USER_ERRNOS = frozenset({errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ELOOP,
                         errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG})


def exit_code_for(exc: BaseException) -> int:
    """Print one short line for ``exc`` and return the exit status it deserves.

    :class:`InvphysError` is the user's to fix (``error: ...``, exit 2); anything else is ours
    (``internal error: <type>: <msg> (run with --debug for the traceback)``, exit 1).
    """
    if isinstance(exc, InvphysError):
        console.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
        return EXIT_USER_ERROR
    if isinstance(exc, OSError) and exc.errno in USER_ERRNOS:
        where = f"{exc.filename!s}: " if exc.filename is not None else ""
        console.print(f"[bold red]error:[/] {escape(where + (exc.strerror or str(exc)))}", soft_wrap=True)
        return EXIT_USER_ERROR
    message = " ".join(str(exc).split()) or "(no message)"
    if len(message) > 300:
        message = message[:297] + "..."
    console.print(f"[bold red]internal error:[/] {type(exc).__name__}: {escape(message)} "
                  "(run with --debug for the traceback)", soft_wrap=True)
    return EXIT_INTERNAL_ERROR


def handle_errors(func: F) -> F:
    """Turn any exception of a command into one short line: exit 2 for user errors, 1 for bugs.

    With ``invphys --debug ...`` the traceback is shown instead.
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except KeyboardInterrupt as exc:
            if debug_enabled():
                raise
            raise typer.Exit(interrupted(exc)) from None
        except Exception as exc:
            if debug_enabled():
                raise
            raise typer.Exit(exit_code_for(exc)) from None

    return wrapper  # type: ignore[return-value]


def interrupted(exc: BaseException | None = None) -> int:
    """Print the one line a stop by signal deserves (``interrupted``; ``terminated`` for SIGTERM) and
    return its exit status (130; 143)."""
    word, code = getattr(exc, "word", "interrupted"), getattr(exc, "exit_code", EXIT_INTERRUPTED)
    sys.stderr.write(f"{word}\n")
    sys.stderr.flush()
    return int(code)


def escape(text: str) -> str:
    from rich.markup import escape as _escape

    return _escape(text)


def emit(data: Any, as_json: bool, render: Callable[[Any], None] | None = None, status_only: bool = False) -> None:
    """Print ``data`` as JSON on stdout when ``as_json``, else call ``render(data)`` (or pretty-print).

    ``status_only``: the rendering only says that the command worked (``finished``, ``valid``); ``-qq``
    leaves it out (the exit status says it). JSON asked for is always printed.
    """
    if as_json:
        sys.stdout.write(json.dumps(data, indent=2, default=str) + "\n")
    elif status_only and silent():
        return
    elif render is not None:
        render(data)
    else:
        out_console.print(data)
