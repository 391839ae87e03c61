"""``invphys export RUN --out DIR``: copy a run's inverter bundle to a directory of its own (checked).

``invphys export --upgrade OLD --out DIR [--trust-pickles]`` converts a bundle written by an older invphys
(format 1, whose NPE posterior and PPO policies were pickles) into the current format, where every
weight is a tensor; converting loads each pickle once, which runs code stored in it.

Export never destroys data: ``--out`` may not be, contain or lie inside the source, nor lie inside another
bundle or under a file; ``--force`` replaces only an existing inverter bundle; the copy is made in a
temporary sibling, verified, and only then swapped in, so a failed export leaves ``--out`` as it was.
"""

from __future__ import annotations

from pathlib import Path

import typer

from invphys.cli.common import emit, escape, handle_errors, out_console


def register(app: typer.Typer) -> None:
    app.command("export")(export)


@handle_errors
def export(
    run: Path = typer.Argument(..., help="run directory of `invphys run` (holds inverter/), or a bundle"),
    out: Path = typer.Option(..., "--out", "-o", help="where to write the bundle (a new or empty directory)"),
    force: bool = typer.Option(False, "--force", help="replace an existing bundle at OUT (never anything else)"),
    upgrade: bool = typer.Option(False, "--upgrade", help="convert a bundle of an older invphys (format 1)"),
    trust_pickles: bool = typer.Option(
        False, "--trust-pickles",
        help="with --upgrade: load the old bundle's pickled parts once, which RUNS CODE stored in them; "
             "only for a bundle from a source you trust"),
    as_json: bool = typer.Option(False, "--json", help="machine-readable output"),
) -> None:
    """Copy a run's inverter bundle to OUT (checked: it must load), or convert an older bundle (--upgrade)."""
    from invphys.core.errors import InvphysError
    from invphys.inverter.bundle import Bundle
    from invphys.inverter.manifest import MANIFEST_FILE
    from invphys.inverter.writer import BUNDLE_DIR, copy_bundle, export_destination, upgrade_bundle

    if trust_pickles and not upgrade:
        raise InvphysError("--trust-pickles only applies to --upgrade")
    src = run / BUNDLE_DIR if (run / BUNDLE_DIR / MANIFEST_FILE).is_file() else run
    converted: dict[str, str] = {}
    if upgrade:
        from invphys.inverter.manifest import read_manifest

        read_manifest(src, verify=False, allow_legacy=True)  # a clear error for something that is no bundle
        export_destination(src, out, force)
        converted = upgrade_bundle(src, out, trust_pickles)
        bundle = Bundle(out)
    else:
        bundle = Bundle(src)  # raises a clear error for a run without a bundle, or a broken one
        export_destination(src, out, force)
        copy_bundle(src, out, bundle.manifest["files"])
    m = bundle.manifest
    data = {"bundle": str(out), "source": str(src), "bundle_id": m.get("bundle_id"),
            "methods": list(m["methods"]), "default_method": m.get("default_method"),
            "size_bytes": sum(p.stat().st_size for p in out.rglob("*") if p.is_file()), "converted": converted}
    emit(data, as_json, lambda d: out_console.print(
        f"[green]{'upgraded' if upgrade else 'exported'}[/] {escape(str(src))} -> {escape(str(out))} "
        f"({d['size_bytes'] / 1e6:.1f} MB, methods: {', '.join(d['methods'])}; default {d['default_method']})"
        + "".join(f"\n  {escape(k)}: {escape(v)}" for k, v in converted.items())))
