"""``invphys invert BUNDLE``: answer a target with material parameters; ``invphys export RUN --out DIR``."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import typer

from invphys.cli.common import console, emit, escape, handle_errors, out_console
from invphys.core.errors import InvphysError


def register(app: typer.Typer) -> None:
    app.command("invert")(invert)
    app.command("export")(export)


def _options(items: list[str]) -> dict[str, Any]:
    """``--sim-option key=value`` items as a dict (values parsed as YAML scalars: 1, 0.5, true, cpu)."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise InvphysError(f"--sim-option {item!r}: expected key=value")
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            out[key.strip()] = value
    return out


@handle_errors
def invert(
    bundle: Path = typer.Argument(..., help="inverter bundle directory (e.g. inverters/orange_peel_paper)"),
    target: str | None = typer.Option(None, "--target", "-t", help="JSON, YAML or CSV file of one or many targets"),
    feature: list[str] = typer.Option(None, "--feature", "-f", help="NAME=VALUE of one target feature (repeat)"),
    observed: list[str] = typer.Option(None, "--observed", help="saved trajectory (.npz or run directory)"),
    partial: bool = typer.Option(False, "--partial", help="allow missing features (left out of R)"),
    method: str | None = typer.Option(None, "--method", "-m", help="bundle method or installed optimiser"),
    top_k: int = typer.Option(1, "--top-k", "-k", min=1, help="diverse candidates per target"),
    refine: int = typer.Option(0, "--refine", min=0, help="CMA-ES surrogate evaluations refining each candidate"),
    validate: bool = typer.Option(False, "--validate", help="re-run the simulator on the answers (R_actual)"),
    sim_option: list[str] = typer.Option(None, "--sim-option", help="simulator config KEY=VALUE for --validate"),
    seed: int = typer.Option(0, "--seed", help="seed of stochastic rollouts and optimisers"),
    allow_mismatch: bool = typer.Option(False, "--allow-mismatch",
                                        help="load a bundle made with another simulator version"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output on stdout"),
) -> None:
    """Answer targets (features by name) with material parameters from a trained inverter bundle."""
    from invphys.inverter import load_inverter
    from invphys.inverter.targets import cli_targets

    inv = load_inverter(bundle, strict=not allow_mismatch)
    for note in inv.notes:
        console.print(f"[yellow]warning:[/] {escape(note)}", soft_wrap=True)
    targets = cli_targets(inv, target, feature or [], observed or [], partial)
    results = inv.invert_many(targets, method=method, top_k=top_k, refine=refine, seed=seed)
    for r in results:
        for w in r.warnings:
            console.print(f"[yellow]warning:[/] target {escape(r.label)}: {escape(w)}", soft_wrap=True)
    if validate:
        _validate(inv, results, _options(sim_option or []))
    data = {"bundle": str(bundle), "method": results[0].method, "results": [r.to_dict() for r in results]}
    emit(data, as_json, lambda _: [_render(r) for r in results])


def _validate(inv: Any, results: list[Any], overrides: dict[str, Any]) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    total = sum(len(r.candidates) for r in results)
    with Progress(TextColumn("validating"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=False) as bar:
        task = bar.add_task("validating", total=total)
        inv.validate(results, overrides=overrides, on_run=lambda _i: bar.advance(task))


def _render(result: Any) -> None:
    from rich.table import Table

    d = result.to_dict()
    out_console.print(f"[bold]target {escape(d['target'])}[/] - method {escape(d['method'])}, "
                      f"{d['evaluations']} surrogate evaluations, {d['wall_time_s'] * 1e3:.1f} ms")
    for c in d["candidates"]:
        head = f"candidate {c['rank']} ({escape(c['source'])}): R_surr {c['r_surrogate']:.3f}"
        if "r_actual" in c:
            head += (f", R_actual {c['r_actual']:.3f}, gap {c['gap']:+.3f}" if c["r_actual"] is not None
                     else f", validation failed: {escape(str(c.get('failure')))}")
        out_console.print(head)
        params = Table("parameter", "value", "unit")
        for name, p in c["parameters"].items():
            params.add_row(name, f"{p['value']:.5g}", p["unit"] or "-")
        out_console.print(params)
        feats = Table("feature", "target", "predicted", "± std", "unit", *(["actual"] if "r_actual" in c else []))
        for name, f in c["features"].items():
            row = [name, "-" if f["target"] is None else f"{f['target']:.5g}", f"{f['predicted']:.5g}",
                   f"{f['std']:.2g}", f["unit"]]
            if "r_actual" in c:
                row.append("-" if f.get("actual") is None else f"{f['actual']:.5g}")
            feats.add_row(*row)
        out_console.print(feats)
    if "spread" in d:
        wide = [k for k, v in d["spread"].items() if v > 0.25]
        if wide:
            out_console.print(f"candidates disagree on (normalised spread > 0.25): {', '.join(wide)}")


@handle_errors
def export(
    run: Path = typer.Argument(..., help="run directory of `invphys run` (holds inverter/)"),
    out: Path = typer.Option(..., "--out", "-o", help="where to write the bundle (a new or empty directory)"),
    force: bool = typer.Option(False, "--force", help="replace an existing bundle at OUT"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
) -> None:
    """Copy a run's inverter bundle to OUT (checked: it must load)."""
    from invphys.inverter.bundle import Bundle
    from invphys.inverter.manifest import MANIFEST_FILE
    from invphys.inverter.writer import BUNDLE_DIR

    src = run / BUNDLE_DIR if (run / BUNDLE_DIR / MANIFEST_FILE).is_file() else run
    bundle = Bundle(src)  # raises a clear error for a run without a bundle, or a broken one
    if out.is_file() or (out.is_dir() and any(out.iterdir())):
        if not force:
            raise InvphysError(f"{out} exists and is not empty; pass --force to replace the bundle there")
        if out.is_file() or not (out / MANIFEST_FILE).is_file():
            raise InvphysError(f"{out} is not an inverter bundle; refusing to replace it")
        if out.resolve() == src.resolve():
            raise InvphysError(f"{out} is the bundle being exported")
        shutil.rmtree(out)
    shutil.copytree(src, out, dirs_exist_ok=True)
    Bundle(out)  # the copy verifies
    m = bundle.manifest
    data = {"bundle": str(out), "source": str(src), "bundle_id": m.get("bundle_id"),
            "methods": list(m["methods"]), "default_method": m.get("default_method"),
            "size_bytes": sum(p.stat().st_size for p in out.rglob("*") if p.is_file())}
    emit(data, as_json, lambda d: out_console.print(
        f"[green]exported[/] {escape(str(src))} -> {escape(str(out))} ({d['size_bytes'] / 1e6:.1f} MB, "
        f"methods: {', '.join(d['methods'])}; default {d['default_method']})"))
