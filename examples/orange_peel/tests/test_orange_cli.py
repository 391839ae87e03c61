"""``invphys simulate`` and ``invphys render`` with the real orange peel (tiny preset, a few frames)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("taichi")
from typer.testing import CliRunner

from invphys.cli import app

runner = CliRunner()


def test_simulate_then_render(tmp_path) -> None:
    out = tmp_path / "sim"
    params = tmp_path / "params.json"
    params.write_text(json.dumps([{"E": 800}, {"E": 800, "sigma_s": 0.5}]))
    res = runner.invoke(app, ["simulate", "--simulator", "orange_peel", "--backend", "taichi", "--preset", "tiny",
                              "--arch", "cpu", "--params", str(params), "--config", '{"frames": 15}',
                              "--out", str(out), "--render", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    runs = summary["runs"]
    assert [r["params"]["E"] for r in runs] == [800.0, 800.0]
    assert runs[1]["params"]["sigma_s"] == 0.5
    assert runs[0]["params"]["rho"] == pytest.approx(5.25)   # missing -> centre of the space
    assert all(r["ok"] and len(r["features"]) == 12 for r in runs)
    assert runs[0]["stats"]["preset"] == "tiny" and runs[0]["stats"]["substeps"] > 0
    run0 = out / "run_000"
    assert (run0 / "trajectory.npz").exists() and (run0 / "run.json").exists()
    assert (out / "summary.json").exists()
    render = run0 / "render"
    pngs = sorted(render.glob("frame_*.png"))
    assert [p.name for p in pngs] == ["frame_0000.png", "frame_0005.png", "frame_0010.png", "frame_0015.png"]
    assert (render / "animation.gif").stat().st_size > 1000

    # the standalone render command, from the run directory
    res = runner.invoke(app, ["render", str(run0), "--out", str(tmp_path / "r2"), "--json"])
    assert res.exit_code == 0, res.output
    info = json.loads(res.stdout)
    assert info["simulator"] == "orange_peel"  # recorded in the trajectory file
    assert info["images"] == 4 and info["files"] == 4 and info["animation"].endswith(".gif")
    ply = (tmp_path / "r2" / "frame_0015.ply").read_bytes()
    header, _, body = ply.partition(b"end_header\n")
    assert b"element vertex 2112" in header and len(body) == 2112 * 17
    from PIL import Image

    img = np.asarray(Image.open(tmp_path / "r2" / "frame_0000.png").convert("RGB")).reshape(-1, 3).astype(int)
    orange = (np.abs(img - [255, 140, 0]).max(axis=1) < 40).sum()
    assert orange > 500  # intact skin drawn in the paper's orange


def test_simulate_bad_input_exits_2(tmp_path) -> None:
    res = runner.invoke(app, ["simulate", "--simulator", "orange_peel", "--preset", "tiny", "--arch", "cpu", "--params", '{"sigma_i": 2}',
                              "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "sigma_i = 2 is outside its range [0.1, 0.9]" in res.output
    res = runner.invoke(app, ["simulate", "--simulator", "orange_peel", "--preset", "tinyy", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "Did you mean 'tiny'" in res.output
    res = runner.invoke(app, ["simulate", "--simulator", "orange_peel", "--preset", "tiny", "--params", '{"sigma": 0.2}', "--out", str(tmp_path)])
    assert res.exit_code == 2 and "Did you mean" in res.output
    res = runner.invoke(app, ["render", str(tmp_path / "nothing"), "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "no trajectory" in res.output
