"""The ``invphys`` command line (typer + rich).

Commands live in one module each (``invphys/cli/<name>.py``), each exposing ``register(app)``;
:data:`COMMAND_MODULES` lists them. Every command that reports takes ``--json``; bad input exits 2 with
a short message (``invphys --debug ...`` shows the traceback).
"""

from __future__ import annotations

import importlib

import typer

from invphys.cli.common import set_debug

COMMAND_MODULES: tuple[str, ...] = ("core", "dataset", "simulate", "render")

app = typer.Typer(
    name="invphys",
    help="Inverse physics with non-differentiable simulators: datasets, surrogates, latent spaces, optimisers.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(debug: bool = typer.Option(False, "--debug", help="show tracebacks instead of short errors")) -> None:
    set_debug(debug)


for _name in COMMAND_MODULES:
    importlib.import_module(f"invphys.cli.{_name}").register(app)


def main() -> None:
    """Console-script entry point."""
    app()
