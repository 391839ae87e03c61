"""Helpers shared by CLI commands: error handling (exit 2 on bad input) and ``--json`` output."""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import typer
from rich.console import Console

from invphys.core.errors import InvphysError

F = TypeVar("F", bound=Callable[..., Any])

#: human-readable output (tables, progress) goes to stderr so that stdout stays machine-readable
console = Console(stderr=True)
out_console = Console()

_state = {"debug": False}


def set_debug(value: bool) -> None:
    _state["debug"] = value


def debug_enabled() -> bool:
    return _state["debug"]


def handle_errors(func: F) -> F:
    """Turn :class:`InvphysError` (and pydantic/YAML input errors) into a short message and exit 2.

    With ``invphys --debug ...`` the traceback is shown instead.
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except (typer.Exit, typer.Abort, KeyboardInterrupt):
            raise
        except InvphysError as exc:
            if debug_enabled():
                raise
            console.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def escape(text: str) -> str:
    from rich.markup import escape as _escape

    return _escape(text)


def emit(data: Any, as_json: bool, render: Callable[[Any], None] | None = None) -> None:
    """Print ``data`` as JSON on stdout when ``as_json``, else call ``render(data)`` (or pretty-print)."""
    if as_json:
        sys.stdout.write(json.dumps(data, indent=2, default=str) + "\n")
    elif render is not None:
        render(data)
    else:
        out_console.print(data)
