"""The ``invphys`` command line (typer + rich).

Commands live in one module each (``invphys/cli/<name>.py``), each exposing ``register(app)``;
:data:`COMMAND_MODULES` lists them. Every command that reports takes ``--json``; bad input exits 2 with
a short message (``invphys --debug ...`` shows the traceback).
"""

from __future__ import annotations

import importlib

import typer

from invphys.cli.common import configure_logging, debug_enabled, exit_code_for, interrupted, set_debug

COMMAND_MODULES: tuple[str, ...] = ("core", "dataset", "simulate", "render", "invert", "export", "diagnose")

app = typer.Typer(
    name="invphys",
    help="Inverse physics with non-differentiable simulators: datasets, surrogates, latent spaces, optimisers.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # plain click help: flags print without a `<bool>` type, and piped help is not boxed or cut
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _print_version(value: bool) -> None:
    if value:
        from invphys.core.version import __version__

        typer.echo(f"invphys {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="show tracebacks and the back-ends' own log lines"),
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="print the version and exit"),
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, show_default=False,
                                 help="more log lines (-v: debug)"),
    quiet: int = typer.Option(0, "--quiet", "-q", count=True, show_default=False,
                               help="fewer log lines (-q: warnings, -qq: errors)"),
) -> None:
    set_debug(debug)
    configure_logging(verbose, quiet)


for _name in COMMAND_MODULES:
    importlib.import_module(f"invphys.cli.{_name}").register(app)


def main() -> None:
    """Console-script entry point: any exception that escapes a command becomes one line (exit 2 or 1)."""
    try:
        app()
    except KeyboardInterrupt as exc:
        raise SystemExit(interrupted(exc)) from None
    except Exception as exc:
        if debug_enabled():
            raise
        raise SystemExit(exit_code_for(exc)) from None
