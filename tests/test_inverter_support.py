"""A small real run (toy oscillator) whose inverter bundle the inverter tests share.

The run is built once per test session under pytest's base temporary directory; the runner's stage
cache makes later builds (from other test modules) instant.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import pytest
import yaml

SPEC = """
name: inverter-toy
description: toy bundle for the inverter tests
seed: 3
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 160, batch_size: 40}
surrogate: {type: ensemble, members: 3, hidden: [32, 32, 16], max_epochs: 60, patience: 20, dropout: 0.0}
latent_models:
  flow: {type: realnvp, latent_dim: 2, max_epochs: 10}
  vae: {type: vae, latent_dim: 2, max_epochs: 10}
optimizers:
  cma: {type: cma_es, budget: 200}
  gc: {type: gc_ppo, total_timesteps: 1024, n_steps: 64, n_envs: 4, net_arch: [32, 32]}
  gc_flow: {type: gc_ppo, space: flow, total_timesteps: 512, n_steps: 64, n_envs: 4, net_arch: [16, 16]}
  ws: {type: warm_start, policy: gc, budget: 60}
targets: {n: 4, validate: 2}
validator: {type: simulator}
stages: [dataset, train, invert, validate]
"""


def spec_dict() -> dict:
    data = yaml.safe_load(SPEC)
    try:  # the evaluation section (when this invphys has one) adds dataset baselines; not needed here
        from invphys.core.spec import ExperimentSpec

        if "evaluation" in ExperimentSpec.model_fields:
            data["evaluation"] = {"baselines": {}}
    except ImportError:
        pass
    return data


def toy_run(base: Path) -> Path:
    """The run directory (built on first use)."""
    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    out = base / "inverter_toy_run"
    run_spec(validate_spec(spec_dict()), out, progress=False, console=Console(file=io.StringIO()))
    return out


@pytest.fixture(scope="module", name="bundle")
def toy_bundle_fixture(tmp_path_factory) -> Path:
    """The toy run's inverter bundle (import this fixture into a test module: it is named ``bundle``)."""
    return toy_run(tmp_path_factory.getbasetemp()) / "inverter"


@pytest.fixture(scope="module", name="inv")
def toy_inverter_fixture(bundle: Path) -> Any:
    """The toy bundle loaded (named ``inv``)."""
    import invphys

    return invphys.load_inverter(bundle)


def npe_toy_bundle(out: Path, name: str, seed: int, max_epochs: int, **dataset: Any) -> Path:
    """A dataset + train + invert run of the toy oscillator with a small MDN NPE into ``out``; its bundle's root
    (``dataset``: more keys of the dataset section, e.g. ``test_fraction``)."""
    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    spec = {"name": name, "seed": seed, "simulator": {"type": "test_dataset_toy:ToyOscillator"},
            "dataset": {"n": 200, "batch_size": 50, **dataset},
            "surrogate": {"type": "ensemble", "members": 2, "hidden": [16, 16, 8], "max_epochs": max_epochs,
                          "dropout": 0.0},
            "optimizers": {"npe_best": {"type": "npe", "estimator": "mdn", "hidden_features": 16,
                                        "max_num_epochs": max_epochs, "samples": 16, "answer": "best_surrogate"}},
            "targets": {"n": 2}, "evaluation": {"baselines": {}}, "stages": ["dataset", "train", "invert"]}
    run_spec(validate_spec(spec), out, progress=False, console=Console(file=io.StringIO()))
    return out / "inverter"


def diagnose_app() -> Any:
    """A Typer app holding only ``invphys diagnose`` (for CliRunner)."""
    import typer

    from invphys.cli import diagnose

    app = typer.Typer()

    @app.callback()
    def _root() -> None:
        pass

    diagnose.register(app)
    return app


def paper_bundle(base: Path) -> Path:
    """A private copy of the shipped paper bundle (never the shipped one), upgraded to the pickle-free
    format when the shipped copy still holds an older pickled part."""
    import shutil
    import subprocess
    import sys

    out = base / "paper_bundle"
    if out.is_dir():
        return out
    src = Path(__file__).resolve().parents[1] / "inverters" / "orange_peel_paper"
    manifest = (src / "manifest.yaml").read_text()
    if "npe.pt" in manifest or "policy.zip" in manifest:
        subprocess.run([sys.executable, "-c", "from invphys.cli import main; main()", "export", "--upgrade", str(src), "--out", str(out),
                        "--trust-pickles"], check=True, capture_output=True)
    else:
        shutil.copytree(src, out)
    return out


def paper_inverter(base: Path) -> Any:
    """An inverter on :func:`paper_bundle`'s private copy (tests share one per session base folder)."""
    import invphys

    return invphys.load_inverter(paper_bundle(base))

