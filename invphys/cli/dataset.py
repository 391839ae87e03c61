"""``invphys dataset generate SPEC``, ``invphys dataset info PATH`` and ``invphys dataset verify PATH [--repair]``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from invphys.cli.common import console, emit, escape, handle_errors, interrupted, out_console, quiet
from invphys.core.errors import InvphysError

dataset_app = typer.Typer(help="Generate and inspect simulation datasets (resumable Parquet stores).",
                          no_args_is_help=True)


def register(app: typer.Typer) -> None:
    app.add_typer(dataset_app, name="dataset")


@dataset_app.command("generate")
@handle_errors
def generate(
    spec: Path = typer.Argument(..., help="YAML experiment spec (simulator, features, executor, dataset)"),
    out: Path | None = typer.Option(None, "--out", "-o", help="dataset directory (default: dataset.path)"),
    n: int | None = typer.Option(None, "--n", min=1, help="override dataset.n"),
    batch_size: int | None = typer.Option(None, "--batch-size", min=1, help="override dataset.batch_size"),
    executor: str | None = typer.Option(None, "--executor", help="override the executor (its default config)"),
    limit_minutes: float | None = typer.Option(
        None, "--limit-minutes", min=0.01, help="stop cleanly after about this long; re-run to resume"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
    as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
) -> None:
    """Simulate the spec's dataset into a resumable store: re-running skips rows already stored."""
    from invphys.core.spec import check_output_directory, load_spec
    from invphys.data.generate import generate_from_spec

    s = load_spec(spec)
    updates: dict[str, Any] = {}
    if n is not None:
        updates["n"] = n
    if batch_size is not None:
        updates["batch_size"] = batch_size
    if updates:  # validated like the spec's own values (bounds included)
        from invphys.core.spec import validate_spec

        data = s.model_dump(mode="json", by_alias=True)
        data["dataset"] = {**data["dataset"], **updates}
        s = validate_spec(data, source="--n/--batch-size", references=False)
    if executor is not None:
        s = s.model_copy(update={"executor": {"type": executor}})
    target = out if out is not None else s.dataset.path
    if target is not None:  # a store may be resumed; nothing may go inside a store, a bundle or a file
        check_output_directory(target, "--out" if out is not None else "dataset.path", store_ok=True)
    summary = generate_from_spec(s, out, progress=not (no_progress or quiet()), console=console,
                                 limit_minutes=limit_minutes)
    data = summary.to_dict()
    emit(data, as_json, _render_summary)
    if summary.stop_reason in ("interrupted", "terminated"):
        from invphys.core.errors import Interrupted

        raise typer.Exit(interrupted(Interrupted(summary.stop_reason,
                                                 130 if summary.stop_reason == "interrupted" else 143)))


def _render_summary(d: dict[str, Any]) -> None:
    from rich.table import Table

    status = {"complete": "[green]complete[/]", "time_limit": "[yellow]stopped at the time limit[/]",
              "interrupted": "[yellow]interrupted[/]", "terminated": "[yellow]terminated[/]",
              "incomplete": "[yellow]incomplete[/]"}.get(d["stop_reason"], d["stop_reason"])
    table = Table(title=f"dataset {escape(d['path'])}: {status}", show_header=False)
    table.add_row("this run", f"{d['ran']} runs: [green]{d['ok']} ok[/], [red]{d['failed']} failed[/] "
                  f"in {d['wall_s']:.1f} s ({d['runs_per_hour']:,.0f} runs/h)")
    table.add_row("skipped", f"{d['already_present']} already stored")
    table.add_row("store", f"{d['total_rows']} of {d['requested']} rows: {d['total_ok']} ok, "
                  f"{d['total_failed']} failed")
    table.add_row("devices", ", ".join(d["devices"]) or "-")
    table.add_row("backends", ", ".join(d["backends"]) or "-")
    design = d.get("design") or {}
    for r in design.get("rounds", []):
        r2 = f", surrogate R^2 {r['surrogate_r2']:.3f}" if r.get("surrogate_r2") is not None else ""
        table.add_row(f"adaptive round {r['round'] + 1}",
                      f"trained on {r['training_rows']} rows{r2}; chosen points' disagreement "
                      f"{r['score_mean_chosen']:.3g} (candidates' median {r['score_median_candidates']:.3g})")
    out_console.print(table)
    if not d["complete"]:
        out_console.print("re-run the same command to resume")


@dataset_app.command("info")
@handle_errors
def info(
    path: Path = typer.Argument(..., help="dataset directory"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
) -> None:
    """Summarise a dataset: counts, failures by reason, provenance, feature percentiles."""
    from invphys.core.dataset import DatasetStore

    emit(DatasetStore(path).info(), as_json, _render_info)


def _render_info(d: dict[str, Any]) -> None:
    from rich.table import Table

    ident = d.get("identity") or {}
    out_console.print(
        f"[bold]{escape(d['path'])}[/]: {d['rows']} rows, [green]{d['ok']} ok[/], [red]{d['failed']} failed[/] "
        f"({d['parts']} parts, {d['sessions']} sessions, {d['generation_wall_s']:.1f} s of generation)")
    out_console.print(
        f"simulator {escape(str(ident.get('simulator')))} v{escape(str(ident.get('version')))}, "
        f"preset {escape(str(ident.get('preset') or '-'))}, backend {escape(', '.join(d['backends']) or '-')}, "
        f"device {escape(', '.join(d['devices']) or '-')}; fingerprint {d['fingerprint']}")
    design = d.get("design")
    if design:
        a = design.get("adaptive") or {}
        out_console.print(
            f"adaptive design: {a.get('initial')} {escape(str(a.get('sampler')))} runs, then "
            f"{len(design.get('rounds', []))} of {a.get('rounds')} rounds planned "
            f"(surrogate {escape(str((a.get('surrogate') or {}).get('type')))})"
            if a else f"adaptive design: {escape(str(design.get('problem')))}")
    if d["failures_by_reason"]:
        failures = Table("failures", "reason", title="failures by reason")
        for reason, count in d["failures_by_reason"].items():
            failures.add_row(str(count), escape(reason))
        out_console.print(failures)
    table = Table("feature", "p5", "p50", "p95", title="features over ok rows")
    for name, p in d["features"].items():
        table.add_row(name, *("-" if p[k] is None else f"{p[k]:.4g}" for k in ("p5", "p50", "p95")))
    out_console.print(table)


@dataset_app.command("verify")
@handle_errors
def verify(
    path: Path = typer.Argument(..., help="dataset directory"),
    repair: bool = typer.Option(False, "--repair", help="quarantine bad parts into _quarantine/, adopt good "
                                "unlisted ones and rewrite the manifest"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
) -> None:
    """Check every part against the manifest (missing, corrupt, foreign, duplicated); exit 2 on problems."""
    from invphys.core.dataset import DatasetStore

    store = DatasetStore(path)
    try:
        report = store.repair() if repair else store.verify()
    except OSError as exc:  # a read-only store or disk: nothing was half-moved (moves are renames)
        raise InvphysError(f"cannot {'repair' if repair else 'verify'} {str(path)!r}: {exc.strerror or exc}"
                           f"{f' ({exc.filename})' if exc.filename else ''}") from None
    data = report.to_dict()
    emit(data, as_json, _render_verify)
    if not report.ok:
        n = len(data["problems"])
        raise InvphysError(f"{path}: {n} problem{'s' if n != 1 else ''} found"
                           f"{'' if repair else '; `invphys dataset verify PATH --repair` quarantines bad parts'}")


def _render_verify(d: dict[str, Any]) -> None:
    for action in d["actions"]:
        out_console.print(f"repaired: {escape(action)}")
    for p in d["problems"]:
        rows = f", {p['rows']} rows" if p["rows"] is not None else ""
        out_console.print(f"[red]{escape(p['kind'])}[/]: {escape(p['part'])} ({escape(p['detail'])}{rows})")
    if not d["has_manifest"]:
        out_console.print("[yellow]no manifest[/] (a store written before manifests existed): "
                          "`invphys dataset verify PATH --repair` writes one")
    state = "[green]ok[/]" if d["ok"] else "[red]problems found[/]"
    hint = "" if d["ok"] or d["actions"] else "; `--repair` quarantines bad parts and rebuilds the manifest"
    out_console.print(f"{escape(d['path'])}: {state}: {d['parts']} good parts, {d['rows']} rows{hint}")
