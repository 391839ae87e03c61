"""``invphys simulate``: run a simulator on one or more parameter vectors and print their features."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from invphys.cli.common import console, emit, handle_errors
from invphys.core.atomic import output_directory
from invphys.core.errors import InvphysError
from invphys.core.results import DEFAULT_MAX_FRAMES

#: the largest ``--params`` file read
MAX_PARAMS_BYTES = 16 * 2**20


def parse_params(text: str | None, space: Any) -> list[dict[str, float]]:
    """``--params`` as a list of ``{name: value}`` dicts: a JSON object, a JSON list of objects, or a
    path to a JSON file holding either. ``None`` means one run at the centre of the space."""
    if text is None or not text.strip():
        return [{}]
    raw: Any
    candidate = Path(text)
    stripped = text.strip()
    if not stripped.startswith(("{", "[")) and candidate.exists():
        if not candidate.is_file():
            kind = "a directory" if candidate.is_dir() else "not a regular file"
            raise InvphysError(f"--params {text!r} is {kind}; give JSON or the path of a JSON file")
        if candidate.stat().st_size > MAX_PARAMS_BYTES:
            raise InvphysError(f"--params file {text!r} is larger than {MAX_PARAMS_BYTES // 2**20} MiB")
        try:
            raw = json.loads(candidate.read_text())
        except UnicodeDecodeError:
            raise InvphysError(f"--params file {text!r} is not UTF-8 text") from None
        except json.JSONDecodeError as exc:
            raise InvphysError(f"--params file {candidate} is not valid JSON: {exc}") from None
    else:
        try:
            raw = json.loads(stripped)
        except json.JSONDecodeError as exc:
            if not stripped.startswith(("{", "[")):
                raise InvphysError(f"--params {text!r} is neither JSON nor an existing file") from None
            raise InvphysError(f"--params is not valid JSON: {exc}") from None
    rows = raw if isinstance(raw, list) else [raw]
    if not rows or not all(isinstance(r, dict) for r in rows):
        raise InvphysError("--params must be a JSON object or a list of objects mapping names to values "
                           f"({', '.join(space.names)})")
    return rows


def _config_error(exc: Exception, what: str) -> InvphysError:
    from pydantic import ValidationError

    if isinstance(exc, ValidationError):
        parts = [f"{'.'.join(str(p) for p in e['loc']) or what}: {e['msg']}" for e in exc.errors()]
        return InvphysError(f"invalid {what} settings: " + "; ".join(parts))
    return InvphysError(str(exc))


def default_simulator(name: str | None) -> str:
    """``name``, or the only installed simulator when ``name`` is None (else a clear error)."""
    if name:
        return name
    from invphys import registry

    installed = registry.names("simulator")
    if len(installed) == 1:
        return installed[0]
    if not installed:
        raise InvphysError("no simulator plugin is installed (see docs/writing-a-simulator.md); "
                           "`invphys plugins` lists what is")
    raise InvphysError(f"several simulators are installed ({', '.join(installed)}): name one with --simulator")


def run_simulation(simulator: str | None, params: str | None, out: Path, *, backend: str | None = None,
                   preset: str | None = None, arch: str | None = None, config: str | None = None,
                   render: bool = False, extractor: str | None = None,
                   max_frames: int = DEFAULT_MAX_FRAMES) -> dict[str, Any]:
    """Simulate, extract features, write ``out/run_XXX/`` folders and ``out/summary.json``.

    The Python API behind ``invphys simulate``; returns the summary dict. ``simulator`` None picks
    the only installed simulator. Each run folder holds ``run.json`` and ``trajectory.npz`` (the
    framework's trajectory file, :mod:`invphys.core.trajectory_io`); with ``render``, ``render/``
    holds what the simulator's :meth:`~invphys.core.interfaces.Simulator.render` drew (at most
    ``max_frames`` frames).
    """
    from pydantic import ValidationError

    from invphys import registry
    from invphys.core.trajectory_io import TRAJECTORY_FILE, save_trajectory

    if max_frames < 1:
        raise InvphysError(f"--max-frames must be at least 1, not {max_frames}")
    block: dict[str, Any] = {"type": default_simulator(simulator)}
    if config:
        try:
            extra = json.loads(config)
        except json.JSONDecodeError as exc:
            raise InvphysError(f"--config is not valid JSON: {exc}") from None
        if not isinstance(extra, dict):
            raise InvphysError("--config must be a JSON object")
        block.update(extra)
    for key, value in (("backend", backend), ("preset", preset), ("arch", arch)):
        if value is not None:
            block[key] = value
    try:
        sim = registry.create("simulator", block)
    except ValidationError as exc:
        raise _config_error(exc, "simulator") from None
    space = sim.parameter_space()
    centre = space.to_mapping(space.center())
    rows = [space.from_mapping(r, defaults=centre) for r in parse_params(params, space)]
    import numpy as np

    ex_name = extractor or sim.default_feature_extractor()
    ex = registry.create("feature_extractor", ex_name) if ex_name else None
    from invphys.core.spec import check_output_directory

    check_output_directory(out)
    output_directory(out)
    results = sim.simulate(np.stack(rows))
    described = sim.describe()
    runs = []
    for i, res in enumerate(results):
        run_dir = out / f"run_{i:03d}"
        run_dir.mkdir(parents=True, exist_ok=True)
        entry: dict[str, Any] = {"run": run_dir.name, "ok": res.ok, "failure": res.failure,
                                 "params": space.to_mapping(res.params), "stats": res.stats.to_dict()}
        if res.ok and res.trajectory is not None:
            save_trajectory(res.trajectory, run_dir / TRAJECTORY_FILE, simulator=described)
            if ex is not None:
                entry["features"] = dict(zip(ex.feature_names, map(float, ex.extract(res.trajectory)),
                                             strict=True))
            if render:
                done = sim.render(res.trajectory, run_dir / "render", max_frames=max_frames)
                entry["render"] = {"animation": None if done.animation is None else str(done.animation),
                                   "images": len(done.images), "dir": str(run_dir / "render")}
        (run_dir / "run.json").write_text(json.dumps(entry, indent=2, default=str))
        runs.append(entry)
    summary = {"simulator": described, "extractor": ex_name, "runs": runs}
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _print(summary: dict[str, Any]) -> None:
    from rich.table import Table

    runs = summary["runs"]
    names: list[str] = []
    for r in runs:
        names = list(r.get("features", {})) or names
    table = Table(title=f"{summary['simulator']['simulator']} ({len(runs)} run(s))")
    table.add_column("feature")
    for r in runs:
        table.add_column(r["run"], justify="right")
    for n in names:
        table.add_row(n, *[f"{r['features'][n]:.4g}" if "features" in r else "-" for r in runs])
    table.add_row("status", *["ok" if r["ok"] else f"FAILED: {r['failure']}" for r in runs])
    table.add_row("substeps", *[str(r["stats"]["substeps"]) for r in runs])
    table.add_row("wall time (s)", *[f"{r['stats']['wall_time_s']:.2f}" for r in runs])
    console.print(table)


def register(app: typer.Typer) -> None:
    """Add ``invphys simulate`` to ``app``."""

    @app.command("simulate")
    @handle_errors
    def simulate(
        simulator: str | None = typer.Option(None, "--simulator", help="simulator plugin name (default: the "
                                             "only installed simulator)"),
        params: str | None = typer.Option(None, "--params", help="JSON object, JSON list of objects, or a "
                                          "JSON file; missing parameters take the centre of the space"),
        out: Path = typer.Option(..., "--out", help="output directory (run_XXX/ folders, summary.json)"),
        backend: str | None = typer.Option(None, "--backend", help="simulator backend (e.g. taichi)"),
        preset: str | None = typer.Option(None, "--preset", help="simulator preset (e.g. tiny, quick, paper)"),
        arch: str | None = typer.Option(None, "--arch", help="cpu, cuda or auto"),
        config: str | None = typer.Option(None, "--config", help="extra simulator settings as a JSON object"),
        render: bool = typer.Option(False, "--render", help="also draw each run with the simulator's renderer"),
        max_frames: int = typer.Option(DEFAULT_MAX_FRAMES, "--max-frames", help="at most this many frame "
                                       "images per run with --render"),
        as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
    ) -> None:
        """Simulate parameter vectors, save trajectories and print their features."""
        summary = run_simulation(simulator, params, out, backend=backend, preset=preset, arch=arch,
                                 config=config, render=render, max_frames=max_frames)
        emit(summary, as_json, _print)
        failed = [r for r in summary["runs"] if not r["ok"]]
        if failed:  # the simulator's answer for these parameters: exit 2 (1 is for bugs)
            raise InvphysError(f"{len(failed)} of {len(summary['runs'])} simulation(s) failed: "
                               f"{failed[0]['run']}: {failed[0]['failure']}")
