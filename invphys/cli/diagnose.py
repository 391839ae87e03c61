"""``invphys diagnose BUNDLE --out DIR``: is the bundle as sure as it says? (docs/diagnostics.md)"""

from __future__ import annotations

from pathlib import Path

import typer

from invphys.cli.common import emit, escape, handle_errors, out_console
from invphys.core.errors import InvphysError


def register(app: typer.Typer) -> None:
    app.command("diagnose")(diagnose)


@handle_errors
def diagnose(
    bundle: Path = typer.Argument(..., help="inverter bundle directory"),
    out: Path = typer.Option(None, "--out", "-o", help="write the report here (a new or empty directory)"),
    write: bool = typer.Option(False, "--write", help="also store it in the bundle's diagnostics/ folder "
                                                      "(answers then use its recalibration and thresholds)"),
    data: list[Path] = typer.Option([], "--data", help="dataset store(s) to draw held-out rows from (repeat; "
                                                       "default: the bundle's dataset and the stores beside it)"),
    rows: int = typer.Option(None, "--rows", min=20, help="use at most this many held-out rows (first by key)"),
    draws: int = typer.Option(1000, "--draws", min=10, max=100_000, help="posterior draws per row"),
    seed: int = typer.Option(0, "--seed", min=0, help="seed of the posterior draws and bootstraps"),
    method: str = typer.Option(None, "--method", help="the method whose posterior is checked (default: the "
                                                      "bundle's default or first with a posterior)"),
    failures: str = typer.Option(None, "--failures", help="FILE[:SET]: held-out targets' default answers re-simulated "
                                 "(bench_user_targets.py --validate --per-target-out); fits the answer-level failure "
                                 "warning (default: keep the bundle's stored one)"),
    check_stored: bool = typer.Option(False, "--check-stored", help="check the bundle's STORED recalibration (no "
                                      "refit) on held-out rows its stored diagnosis did not use; --write adds the "
                                      "check to its diagnostics"),
    as_json: bool = typer.Option(False, "--json", help="print the report as JSON"),
) -> None:
    """Measure a bundle on rows it never trained on: coverage, TARP, SBC, recalibration, OOD, error bars."""
    from invphys.evaluation.diagnose import diagnose as run
    from invphys.evaluation.diagnose_report import summary_markdown, write_into_bundle, write_report
    from invphys.inverter import load_inverter

    if out is None and not write:
        raise InvphysError("say where the report goes: --out DIR, and/or --write (into the bundle)")
    if out is not None and (out.is_file() or (out.is_dir() and any(out.iterdir()))):
        raise InvphysError(f"{out} exists and is not empty; name a new or empty directory")
    if check_stored:
        if method or failures:
            raise InvphysError("--check-stored checks the stored posterior block: --method and --failures do not apply")
        return _check(bundle, out, write, data, rows, draws, seed, as_json)
    inv = load_inverter(bundle)
    result = run(inv, stores=data or None, rows=rows, draws=draws, seed=seed, method=method, failures=failures)
    written = [str(p) for p in write_report(result, out)] if out is not None else []
    if write:
        written.append(str(write_into_bundle(result, inv.bundle.root)))
    emit({**result.report, "written": written}, as_json,
         lambda d: out_console.print(escape(summary_markdown(result.report)) + "\nwritten: "
                                     + escape(", ".join(written))))


def _check(bundle: Path, out: Path | None, write: bool, data: list[Path], rows: int | None, draws: int, seed: int,
           as_json: bool) -> None:
    """``--check-stored``: the stored recalibration on unused held-out rows, to ``out`` and/or the bundle."""
    from invphys.evaluation.diagnose_report import write_check_into_bundle
    from invphys.evaluation.stored_check import check_markdown, check_stored, stored_diagnostics, write_check
    from invphys.inverter import load_inverter

    stored_diagnostics(bundle)  # no diagnostics: say so before loading anything heavy
    inv = load_inverter(bundle)
    check, rebuilt = check_stored(inv, stores=data or None, rows=rows, draws=draws, seed=seed)
    written = [str(p) for p in write_check(check, out)] if out is not None else []
    if write:
        written.append(str(write_check_into_bundle(check, inv.bundle.root, rebuilt)))
    emit({**check, "written": written}, as_json,
         lambda d: out_console.print(escape(check_markdown(check)) + "\nwritten: " + escape(", ".join(written))))
