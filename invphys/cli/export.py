"""``invphys export RUN --out DIR``: copy a run's inverter bundle to a directory of its own (checked)."""

from __future__ import annotations

import shutil
from pathlib import Path

import typer

from invphys.cli.common import emit, escape, handle_errors, out_console
from invphys.core.errors import InvphysError


def register(app: typer.Typer) -> None:
    app.command("export")(export)


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
