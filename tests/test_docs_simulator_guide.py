"""The author's guide runs: a package built only from the code blocks of docs/writing-a-simulator.md
installs like a third-party distribution, passes its own conformance tests and runs the whole pipeline
(dataset -> train -> invert -> validate -> report) with no framework change."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
GUIDE = ROOT / "docs" / "writing-a-simulator.md"
EXAMPLE = ROOT / "examples" / "toy_spring"
BLOCK = re.compile(r'^```\w+ title="([^"]+)"\n(.*?)^```$', re.S | re.M)

pytest.importorskip("torch")
pytest.importorskip("cma")
pytest.importorskip("setuptools")


def guide_files() -> dict[str, str]:
    """``{relative path: text}`` of every titled code block of the guide."""
    return {path: body for path, body in BLOCK.findall(GUIDE.read_text())}


def test_the_guide_shows_the_whole_example_package() -> None:
    docs = guide_files()
    skip = {"build", "__pycache__"}
    files = {p.relative_to(EXAMPLE).as_posix() for p in EXAMPLE.rglob("*")
             if p.is_file() and p.suffix in (".py", ".toml", ".yaml")
             and not skip & set(p.parts) and not any(part.endswith(".egg-info") for part in p.parts)}
    assert set(docs) == files
    for rel, body in docs.items():
        assert (EXAMPLE / rel).read_text() == body, f"{rel} differs between the guide and examples/toy_spring"


def _cli(env: dict[str, str], *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "invphys.cli", *args], env=env, cwd=cwd, text=True,
                          capture_output=True, timeout=300)


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The guide's package written to disk and pip-installed into its own folder (not into the venv)."""
    tmp = tmp_path_factory.mktemp("guide")
    pkg = tmp / "toy-spring"
    for rel, body in guide_files().items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(body)
    site = tmp / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(site), str(pkg)], check=True, capture_output=True, timeout=300)
    path = [str(site), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path), "COLUMNS": "200"}
    return tmp, pkg, env


def test_the_installed_package_is_a_plugin_and_passes_its_own_tests(installed) -> None:
    _, pkg, env = installed
    res = _cli(env, "plugins", "--json")
    assert res.returncode == 0, res.stderr
    found = {(p["kind"], p["name"]): p for p in json.loads(res.stdout)}
    assert found[("simulator", "toy_spring")]["distribution"] == "invphys-toy-spring"
    assert found[("feature_extractor", "toy_spring_features")]["distribution"] == "invphys-toy-spring"
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests"], cwd=pkg,
                         env=env, text=True, capture_output=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "3 passed" in res.stdout


def test_simulate_and_render_commands_of_the_guide(installed) -> None:
    tmp, _, env = installed
    out = tmp / "sim"
    res = _cli(env, "simulate", "--simulator", "toy_spring", "--params", '{"k": 200}', "--render",
               "--max-frames", "5", "--out", str(out), "--json")
    assert res.returncode == 0, res.stderr
    run = json.loads(res.stdout)["runs"][0]
    assert run["ok"] and run["features"]["peak_force"] == pytest.approx(200 * 0.05)
    assert len(list((out / "run_000" / "render").glob("frame_*.png"))) == 5
    res = _cli(env, "render", str(out / "run_000"), "--out", str(tmp / "again"), "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["simulator"] == "toy_spring"


def test_the_guide_spec_runs_the_whole_pipeline(installed) -> None:
    tmp, pkg, env = installed
    out = tmp / "run"
    res = _cli(env, "run", str(pkg / "invphys_toy_spring" / "specs" / "quick.yaml"), "--out", str(out))
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    validation = json.loads((out / "validate" / "validation.json").read_text())
    cma = [v for v in validation if v["optimizer"] == "cma_es"]  # (baselines may add rows of their own)
    assert len(cma) == 4 and not any(v["failure"] for v in validation)
    # the recovered parameters, re-simulated, reproduce the targets' behaviour
    assert np.mean([v["r_actual"] for v in cma]) > 0.7  # measured 0.84-0.89 over seeds 0-2
    # the validate stage kept the runs' time series whole, and the report plots them
    from invphys.core.trajectory_io import load_trajectory

    kept = load_trajectory(out / "validate" / "renders" / "t00_target.npz")
    assert set(kept.series) == {"displacement", "force", "energy"} and len(kept.series["force"]) == 401
    md = (out / "report" / "report.md").read_text()
    assert "renders/t00_series.png" in md and "renders/t00.png" in md
    assert (out / "report" / "renders" / "t00_series.png").stat().st_size > 10_000
