"""``invphys render``: draw a simulated run with its simulator's renderer (``Simulator.render``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from invphys.cli.common import console, emit, handle_errors
from invphys.core.errors import InvphysError
from invphys.core.results import DEFAULT_MAX_FRAMES


def parse_options(items: list[str] | None) -> dict[str, Any]:
    """``["azim=30", "ply=false"]`` as ``{"azim": 30, "ply": False}`` (values parsed as JSON, else text)."""
    options: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise InvphysError(f"--option {item!r} is not KEY=VALUE")
        try:
            options[key.strip()] = json.loads(text)
        except json.JSONDecodeError:
            options[key.strip()] = text
    return options


def _simulator(name: str | None, header: dict[str, Any]) -> Any:
    """The simulator that drew the run: ``name``, else the one the file records, else the only one installed;
    built with the recorded config when it is the recorded simulator. None when the recorded simulator is
    not installed (and no ``name`` was given): the generic renderer draws it then."""
    from pydantic import ValidationError

    from invphys import registry
    from invphys.cli.simulate import default_simulator

    recorded = header.get("simulator") or {}
    if not isinstance(recorded, dict) or not isinstance(recorded.get("simulator"), str):
        recorded = {}  # a header that records no usable simulator: as an older file's
    if not name and recorded.get("simulator") and recorded["simulator"] not in registry.names("simulator"):
        return None
    name = name or recorded.get("simulator") or default_simulator(None)
    block: dict[str, Any] = {"type": name}
    if recorded.get("simulator") == name and isinstance(recorded.get("config"), dict):
        block.update(recorded["config"])
    try:
        return registry.create("simulator", block)
    except ValidationError:  # the recorded config no longer fits this version: defaults still draw
        return registry.create("simulator", {"type": name})


def render_run(source: Path, out: Path, *, simulator: str | None = None, max_frames: int = DEFAULT_MAX_FRAMES,
               animation: str = "gif", options: dict[str, Any] | None = None) -> dict[str, Any]:
    """Render a run directory (holding ``trajectory.npz``) or a trajectory ``.npz`` into ``out``; a
    missing, truncated or corrupt file is one :class:`InvphysError` line naming it."""
    from invphys.core.atomic import output_directory
    from invphys.core.trajectory_io import load_with_header

    if animation not in ("gif", "mp4", "none"):
        raise InvphysError(f"--animation must be gif, mp4 or none, not {animation!r}")
    if max_frames < 1:
        raise InvphysError(f"--max-frames must be at least 1, not {max_frames}")
    traj, header = load_with_header(source)
    out = output_directory(out, "--out")
    sim = _simulator(simulator, header)
    if sim is None:
        from invphys.core.trajectory_plot import render_trajectory

        missing = header["simulator"]["simulator"]
        if options:
            raise InvphysError(f"simulator {missing!r} is not installed; the generic renderer takes no options")
        who = f"generic renderer ({missing} is not installed)"
        done = render_trajectory(traj, out, max_frames=max_frames, animation=animation, title=missing)
    else:
        who = sim.name
        done = sim.render(traj, out, max_frames=max_frames, animation=animation, **(options or {}))
    return {"source": str(source), "out": str(out), "simulator": who, "images": len(done.images),
            "files": len(done.files), "animation": None if done.animation is None else str(done.animation)}


def register(app: typer.Typer) -> None:
    """Add ``invphys render`` to ``app``."""

    @app.command("render")
    @handle_errors
    def render(
        source: Path = typer.Argument(..., help="run directory (with trajectory.npz) or a trajectory .npz"),
        out: Path = typer.Option(..., "--out", help="output directory"),
        simulator: str | None = typer.Option(None, "--simulator", help="simulator whose renderer draws it "
                                             "(default: the one recorded in the file, else the only one "
                                             "installed)"),
        max_frames: int = typer.Option(DEFAULT_MAX_FRAMES, "--max-frames", help="at most this many frame images"),
        animation: str = typer.Option("gif", "--animation", help="gif, mp4 (needs imageio-ffmpeg) or none"),
        option: list[str] | None = typer.Option(None, "--option", "-o", help="KEY=VALUE setting of the "
                                                "simulator's renderer (repeatable; e.g. azim=30)"),
        as_json: bool = typer.Option(False, "--json", help="print the result as JSON"),
    ) -> None:
        """Draw a simulated run with its simulator's renderer (frames, an animation, plots)."""
        result = render_run(source, out, simulator=simulator, max_frames=max_frames, animation=animation,
                            options=parse_options(option))
        emit(result, as_json, lambda r: console.print(
            f"{r['simulator']}: wrote {r['images']} image(s), {r['files']} other file(s), "
            f"animation: {r['animation']} -> {r['out']}"))
