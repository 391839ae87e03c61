"""``invphys render``: PNG frames, an animation and ParaView files of a simulated run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from invphys.cli.common import console, emit, handle_errors
from invphys.core.errors import InvphysError


def render_run(source: Path, out: Path, *, azim: float = 60.0, elev: float = 30.0,
               animation: str = "gif", ply: bool = True) -> dict[str, Any]:
    """Render a run directory (holding ``trajectory.npz``) or a trajectory ``.npz`` into ``out``."""
    if animation not in ("gif", "mp4", "none"):
        raise InvphysError(f"--animation must be gif, mp4 or none, not {animation!r}")
    try:
        from invphys_orange_peel.render import render_trajectory
        from invphys_orange_peel.trajio import load_trajectory
    except ImportError as exc:
        raise InvphysError(f"rendering needs the invphys-orange-peel distribution: {exc}") from None
    traj = load_trajectory(source)
    res = render_trajectory(traj, out, azim=azim, elev=elev, animation=animation, ply=ply)
    return {"source": str(source), "out": str(out), "frames": len(res["frames"]), "ply": len(res["ply"]),
            "animation": res.get("animation")}


def register(app: typer.Typer) -> None:
    """Add ``invphys render`` to ``app``."""

    @app.command("render")
    @handle_errors
    def render(
        source: Path = typer.Argument(..., help="run directory (with trajectory.npz) or a trajectory .npz"),
        out: Path = typer.Option(..., "--out", help="output directory"),
        azim: float = typer.Option(60.0, "--azim", help="camera azimuth (degrees)"),
        elev: float = typer.Option(30.0, "--elev", help="camera elevation (degrees)"),
        animation: str = typer.Option("gif", "--animation", help="gif, mp4 (needs imageio-ffmpeg) or none"),
        ply: bool = typer.Option(True, "--ply/--no-ply", help="write .ply files for ParaView"),
        as_json: bool = typer.Option(False, "--json", help="print the result as JSON"),
    ) -> None:
        """Render PNG frames, a GIF/MP4 and .ply files of a run (Fig. 3 colours)."""
        result = render_run(source, out, azim=azim, elev=elev, animation=animation, ply=ply)
        emit(result, as_json, lambda r: console.print(
            f"wrote {r['frames']} frame(s), {r['ply']} .ply file(s), animation: {r['animation']} -> {r['out']}"))
