"""The uncertainty penalty from the spec (optimizers.<label>.uncertainty_penalty) reaches every optimiser
in the invert stage, GC-PPO's training reward included: answers keep their plain R_surr, the penalised
score is recorded, the trained policy remembers its lambda and a changed lambda retrains it."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import yaml

SPEC = """
name: penalty-wiring
seed: 2
stages: [dataset, train, invert]
simulator: {type: "test_dataset_toy:ToyOscillator"}
dataset: {n: 120, batch_size: 40}
surrogate: {type: ensemble, members: 2, hidden: [16, 16, 8], max_epochs: 30, patience: 10, dropout: 0.0}
optimizers:
  cma: {type: cma_es, budget: 80}
  cma_pen: {type: cma_es, budget: 80, uncertainty_penalty: 3.0}
  gc: {type: gc_ppo, total_timesteps: 512, n_steps: 64, n_envs: 4, net_arch: [16, 16], uncertainty_penalty: 1.0}
  ws: {type: warm_start, policy: gc, budget: 40, uncertainty_penalty: 1.0}
targets: {n: 3, validate: 0}
evaluation: {baselines: {}}
"""


def _run(text: str, out, force=()):
    from rich.console import Console

    from invphys.core.spec import parse_spec
    from invphys.pipeline.runner import run_spec

    return run_spec(parse_spec(text), out, progress=False, console=Console(file=io.StringIO()), force=force)


def test_penalty_reaches_every_optimiser_and_gc_ppo_training(tmp_path) -> None:
    from invphys.core.objectives import recovery_reward
    from invphys.pipeline.context import StageContext  # noqa: F401  (import check: the stage's own module)

    out = tmp_path / "run"
    first = _run(SPEC, out)
    rows = json.loads((out / "invert" / "results.json").read_text())
    targets = json.loads((out / "invert" / "targets.json").read_text())
    scales = np.asarray(targets["scales"])
    by = {}
    for r in rows:
        by.setdefault(r["optimizer"], []).append(r)
    assert "uncertainty_penalty" not in by["cma"][0]
    for label in ("cma_pen", "gc", "ws"):
        for r in by[label]:
            assert r["uncertainty_penalty"] > 0
            plain = float(recovery_reward(np.asarray(r["predicted"]), np.asarray(targets["features"][r["target_index"]]),
                                          scales))
            assert r["r_surrogate"] == pytest.approx(plain)  # rows report the plain R_surr
            assert r["in_loop_score"] <= plain + 1e-12  # the optimiser saw R - lambda * std
        assert any(r["in_loop_score"] < r["r_surrogate"] - 1e-6 for r in by[label])  # an ensemble disagrees
    meta = json.loads((out / "invert" / "policies" / "gc" / "gc_ppo.json").read_text())["meta"]
    assert meta["uncertainty_penalty"] == 1.0
    assert not first["invert"]["prepare"]["gc"].get("cached")

    # another lambda for the policy: the cached policy is not reused, it is trained again
    data = yaml.safe_load(SPEC)
    data["optimizers"]["gc"]["uncertainty_penalty"] = 0.5
    again = _run(yaml.safe_dump(data), out)
    assert again["invert"]["prepare"]["gc"]["timesteps"] >= 512 and not again["invert"]["prepare"]["gc"].get("cached")
    assert json.loads((out / "invert" / "policies" / "gc" / "gc_ppo.json").read_text())["meta"][
        "uncertainty_penalty"] == 0.5


def test_penalty_spec_errors() -> None:
    from invphys.core.errors import SpecError
    from invphys.core.spec import parse_spec

    data = yaml.safe_load(SPEC)
    data["optimizers"]["cma_pen"]["uncertainty_penalty"] = -1
    with pytest.raises(SpecError, match="uncertainty_penalty: must be a number >= 0"):
        parse_spec(yaml.safe_dump(data))
    data["optimizers"]["cma_pen"].update(uncertainty_penalty=1.0, evaluator="own_head")
    with pytest.raises(SpecError, match="needs evaluator: shared"):
        parse_spec(yaml.safe_dump(data))


def test_same_penalty_reuses_the_cached_policy(tmp_path) -> None:
    out = tmp_path / "run"
    _run(SPEC, out)
    assert _run(SPEC, out, force=["invert"])["invert"]["prepare"]["gc"]["cached"] is True
