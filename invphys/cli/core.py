"""Core commands: ``plugins``, ``schema``, ``validate`` and ``run``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from invphys.cli.common import console, emit, escape, exit_code_for, handle_errors, out_console, quiet, silent


def register(app: typer.Typer) -> None:
    app.command("plugins")(plugins)
    app.command("schema")(schema)
    app.command("validate")(validate)
    app.command("run")(run)


@handle_errors
def plugins(
    kind: str | None = typer.Option(None, "--kind", help="only this kind (e.g. optimizer)"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
) -> None:
    """List installed plugins: name, kind, distribution and version."""
    from invphys import registry

    rows = [info.to_dict() for info in registry.infos(kind)]

    def render(data: list[dict[str, Any]]) -> None:
        from rich.table import Table

        table = Table("kind", "name", "distribution", "version", "class", title="invphys plugins")
        for r in data:
            table.add_row(r["kind"], r["name"], r["distribution"], r["version"], r["class"])
        out_console.print(table)

    emit(rows, as_json, render)


@handle_errors
def schema(
    out: Path | None = typer.Option(None, "--out", help="write to this file instead of stdout"),
) -> None:
    """Print the JSON Schema of experiment specs, covering the installed plugins' configs."""
    import json

    from invphys.core.atomic import atomic_write_bytes
    from invphys.core.errors import InvphysError
    from invphys.core.spec import json_schema, output_problem

    if out is not None:
        if out.is_dir():
            raise InvphysError(f"--out {str(out)!r} is a directory; name the schema's file (e.g. spec.schema.json)")
        problem = None if out.is_file() else output_problem(out, "--out")
        if problem:
            raise InvphysError(problem)
    text = json.dumps(json_schema(), indent=2)
    if out:
        atomic_write_bytes(out, (text + "\n").encode())
        if not silent():
            console.print(f"schema written to {escape(str(out))}")
    else:
        typer.echo(text)


@handle_errors
def validate(
    spec: Path = typer.Argument(..., help="YAML experiment spec"),
    out: Path | None = typer.Option(None, "--out", "-o", help="also check this run directory as `run --out` "
                                    "would (not in a dataset store or a bundle, not under a file)"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output (also for an invalid spec)"),
) -> None:
    """Validate a spec: shape, every plugin block by its plugin's config, and every reference that can be
    checked without running (feature names, target files, dataset paths); all problems at once."""
    from invphys.core.errors import InvphysError
    from invphys.core.spec import check_output_directory, load_spec

    try:
        s = load_spec(spec)
        if out is not None:
            check_output_directory(out)
    except InvphysError as exc:
        if not as_json:
            raise
        emit({"spec": str(spec), "ok": False, "valid": False, "errors": _errors_of(exc)}, True)
        raise typer.Exit(exit_code_for(exc)) from None
    data = {"spec": str(spec), "ok": True, "valid": True, "errors": [], "name": s.name, "stages": s.stages,
            "plugins": [{"path": p, "kind": k, "type": b.get("type")} for p, k, b in s.plugin_blocks()]}
    emit(data, as_json, lambda d: out_console.print(
        f"[green]valid[/]: {escape(str(spec))} (stages: {', '.join(d['stages'])})"), status_only=True)


def _errors_of(exc: Exception) -> list[dict[str, Any]]:
    """An error as ``[{path, line, message}]``: one entry per located spec problem, else one for the file."""
    from invphys.core.spec import problem_line

    problems = getattr(exc, "problems", None) or []
    lines = getattr(exc, "lines", None) or {}
    if not problems:
        return [{"path": None, "line": None, "message": str(exc)}]
    rows = [{"path": ".".join(path), "line": problem_line(path, lines), "message": message}
            for path, message in problems]
    return sorted(rows, key=lambda row: row["line"] or 0)  # in file order, as the text lists them


@handle_errors
def run(
    spec: Path = typer.Argument(..., help="YAML experiment spec"),
    out: Path = typer.Option(..., "--out", "-o", help="run directory (artifacts are cached and resumed here)"),
    stage: list[str] = typer.Option(None, "--stage", "-s", metavar="STAGE", help="run only these stages (repeatable)"),
    force: list[str] = typer.Option(None, "--force", metavar="STAGE", help="re-run these stages even when cached"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bars (-q implies it)"),
    as_json: bool = typer.Option(False, "--json", help="print the stage summaries as JSON"),
) -> None:
    """Run the stages a spec names, caching each stage's artifacts under OUT and resuming from them."""
    from invphys.pipeline.runner import run_spec

    def on_stage(name: str, status: str, summary: dict[str, Any] | None) -> None:
        if quiet():
            return
        if status == "cached":
            console.print(f"[cyan]- {name}[/]: cached (inputs unchanged)")
        elif status == "start":
            console.rule(f"[bold]{name}")
        else:
            secs = (summary or {}).get("wall_time_s", 0)
            console.print(f"[green]done {name}[/] in {secs:.1f} s")

    from rich.console import Console

    # -q: no progress, no stage or re-run lines (warnings stay); -qq: the runner's warnings go too
    summaries = run_spec(spec, out, stages=stage or None, force=force or (), progress=not (no_progress or quiet()),
                         console=Console(stderr=True, quiet=True) if silent() else console, on_stage=on_stage,
                         quiet=quiet())
    emit(summaries, as_json, lambda d: out_console.print(f"[green]finished[/]: {', '.join(d)} -> {escape(str(out))}"),
         status_only=True)
