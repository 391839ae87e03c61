"""A spec declares the candidate pool and the bundle's default method: `invphys run` ships them (no hand edit)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from test_inverter_support import toy_run

NPE = {"type": "npe", "estimator": "mdn", "hidden_features": 16, "max_num_epochs": 20, "samples": 16,
       "answer": "best_surrogate"}


def _spec(store: Path, **extra: Any) -> dict[str, Any]:
    return {"name": "spec-pool", "seed": 3, "simulator": {"type": "test_dataset_toy:ToyOscillator"},
            "dataset": {"path": str(store)},
            "surrogate": {"type": "ensemble", "members": 2, "hidden": [16, 16, 8], "max_epochs": 30, "dropout": 0.0},
            "optimizers": {"npe_a": NPE, "npe_b": {**NPE, "seed": 1}, "lookup": {"type": "nearest_neighbour"}},
            "targets": {"n": 2}, "stages": ["train", "invert"], **extra}


@pytest.fixture(scope="module")
def store(tmp_path_factory: Any) -> Path:
    return toy_run(tmp_path_factory.getbasetemp()) / "dataset" / "store"


@pytest.fixture(scope="module")
def bundle(store: Path, tmp_path_factory: Any) -> Path:
    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    out = tmp_path_factory.mktemp("spec_pool") / "run"
    spec = _spec(store, pools={"pool_ab": {"posterior": "npe_a", "extra": ["npe_b"], "moves": 8}},
                 default_method="pool_ab")
    run_spec(validate_spec(spec), out, progress=False, console=Console(file=io.StringIO()))
    return out / "inverter"


def test_the_spec_pool_ships_as_the_default_and_answers_like_a_hand_made_entry(bundle: Path, tmp_path: Path) -> None:
    from invphys.inverter import load_inverter
    from invphys.inverter.manifest import write_manifest

    m = yaml.safe_load((bundle / "manifest.yaml").read_text())
    assert m["default_method"] == "pool_ab"  # without the key: the best held-out policy (an npe or the lookup)
    assert m["methods"]["pool_ab"] == {"type": "pool", "kind": "pool", "space": "raw", "evaluator": "shared",
                                       "config": {"posterior": "npe_a", "extra": ["npe_b"], "moves": 8}}
    y = np.load(bundle / "data" / "test.npz")["y"][:3]
    inv = load_inverter(bundle)
    got = np.array([r.theta for r in inv.invert_many(y, seed=5)])  # the default: the pool
    # the old way: the bundle without the pool, the entry and the default written in by hand after export
    import shutil
    hand = tmp_path / "hand"
    shutil.copytree(bundle, hand)
    hm = yaml.safe_load((hand / "manifest.yaml").read_text())
    del hm["methods"]["pool_ab"]
    hm["default_method"] = "npe_a"
    write_manifest(hand, hm)
    assert load_inverter(hand).default_method == "npe_a"
    hm["methods"]["pool_ab"] = {"type": "pool", "kind": "pool", "space": "raw", "evaluator": "shared",
                                "config": {"posterior": "npe_a", "extra": ["npe_b"], "moves": 8}}
    hm["default_method"] = "pool_ab"
    write_manifest(hand, hm)
    want = np.array([r.theta for r in load_inverter(hand).invert_many(y, seed=5)])
    np.testing.assert_array_equal(got, want)
    # and it is not the posterior's own answer (the pool adds rows and moves)
    assert not np.array_equal(got, np.array([r.theta for r in inv.invert_many(y, method="npe_a", seed=5)]))


@pytest.mark.parametrize(("extra", "message"), [
    ({"pools": {"p": {"posterior": "nope"}}}, "pools.p.posterior: 'nope' is no optimizers label"),
    ({"pools": {"p": {"posterior": "npe_a", "extra": ["npe_c"]}}}, "pools.p.extra: 'npe_c' is no optimizers label"),
    ({"pools": {"p": {"extra": ["npe_a"]}}}, "pools.p.posterior: name the posterior method"),
    ({"pools": {"lookup": {"posterior": "npe_a"}}}, "pools.lookup: label already used"),
    ({"default_method": "npe_z"}, "default_method: 'npe_z' is no optimizers or pools label"),
])
def test_a_bad_pool_or_default_fails_the_spec_check(store: Path, extra: dict[str, Any], message: str) -> None:
    from invphys.core.errors import InvphysError
    from invphys.core.spec import validate_spec

    with pytest.raises(InvphysError, match=message.replace("(", r"\(")):
        validate_spec(_spec(store, **extra))


def test_a_bad_pool_setting_stops_the_run_before_it_writes(store: Path, tmp_path: Path) -> None:
    from invphys.core.errors import InvphysError
    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    for pool, message in (({"posterior": "npe_a", "draws": 0}, "pools.p: pool draws must be a whole number >= 1"),
                          ({"posterior": "npe_a", "wings": 3}, "pools.p: unknown setting.s. wings")):
        with pytest.raises(InvphysError, match=message):
            run_spec(validate_spec(_spec(store, pools={"p": pool})), tmp_path / "out", progress=False)
        assert not (tmp_path / "out").exists()


def test_the_cli_reports_a_bad_default_in_one_line(store: Path, tmp_path: Path) -> None:
    import subprocess
    import sys

    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump(_spec(store, default_method="npe_z")))
    proc = subprocess.run([sys.executable, "-m", "invphys.cli", "run", str(spec), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, cwd=Path(__file__).parent)
    assert proc.returncode == 2, proc.stderr
    assert "default_method: 'npe_z' is no optimizers or pools label" in proc.stderr


def test_changed_pools_rewrite_the_cached_runs_bundle_without_refitting(store: Path, tmp_path: Path) -> None:
    """Pools, default and description are read by the bundle alone: changing them keeps train and invert
    cached (no model refits) yet the run's bundle follows the spec (the old code said "cached" and kept the
    old pool, silently); a second run with the same spec rewrites nothing."""
    import shutil

    from rich.console import Console

    from invphys.core.spec import validate_spec
    from invphys.pipeline.runner import run_spec

    first = _spec(store, pools={"pool_ab": {"posterior": "npe_a", "extra": ["npe_b"]}}, default_method="pool_ab")
    out = tmp_path / "run"
    run_spec(validate_spec(first), out, progress=False, console=Console(file=io.StringIO()))
    policy = out / "invert" / "policies" / "npe_a"
    weights = {p: p.stat().st_mtime_ns for p in policy.rglob("*") if p.is_file()}
    changed = _spec(store, pools={"pool_x": {"posterior": "npe_b", "moves": 4, "exact": True, "margin": 0.03}},
                    default_method="pool_x", description="the pool over npe_b")
    seen: list[tuple[str, str]] = []
    log = io.StringIO()
    run_spec(validate_spec(changed), out, progress=False, console=Console(file=log, width=200),
             on_stage=lambda stage, state, _: seen.append((stage, state)))
    assert seen == [("train", "cached"), ("invert", "cached")]
    assert {p: p.stat().st_mtime_ns for p in policy.rglob("*") if p.is_file()} == weights  # nothing refitted
    m = yaml.safe_load((out / "inverter" / "manifest.yaml").read_text())
    assert m["default_method"] == "pool_x" and "pool_ab" not in m["methods"]
    assert m["methods"]["pool_x"]["config"] == {"posterior": "npe_b", "moves": 4, "exact": True, "margin": 0.03}
    assert m["description"] == "the pool over npe_b" and "bundle rewritten" in log.getvalue()
    # the same spec again: nothing to rewrite
    bundle = out / "inverter" / "manifest.yaml"
    before = bundle.stat().st_mtime_ns
    log2 = io.StringIO()
    run_spec(validate_spec(changed), out, progress=False, console=Console(file=log2, width=200))
    assert bundle.stat().st_mtime_ns == before and "bundle rewritten" not in log2.getvalue()
    shutil.rmtree(out)


def test_diagnose_judges_an_exact_pools_stored_row_answers_by_their_real_r(bundle: Path, tmp_path: Path) -> None:
    """A default pool with ``exact`` answers with stored rows: diagnose's "does not reproduce" label takes their
    real R (known, no surrogate), not the surrogate's R at their parameters (the old code used R_surr for all)."""
    import shutil

    from invphys.evaluation import diagnose as dg
    from invphys.inverter import load_inverter
    from invphys.inverter.manifest import write_manifest

    exact = tmp_path / "exact"
    shutil.copytree(bundle, exact)
    m = yaml.safe_load((exact / "manifest.yaml").read_text())
    m["methods"]["pool_ab"]["config"].update(exact=True, margin=0.99)  # every answer a stored row
    write_manifest(exact, m)
    inv = load_inverter(exact)
    y = np.load(exact / "data" / "test.npz")["y"][:6]
    theta, known = dg._answers(inv, y)
    results = inv.invert_many(y, draws=1)
    assert np.isfinite(known).all()
    np.testing.assert_array_equal(known, [r.r_known for r in results])
    np.testing.assert_array_equal(theta, [r.theta for r in results])
    _, plain = dg._answers(load_inverter(bundle), y)  # the surrogate-scored pool: no stored-row R
    assert np.isnan(plain).all()
    report = dg.diagnose(inv, draws=20).report
    ood = report["ood"]
    assert ood["failure"]["stored_rows_by_real_r"] == report["heldout"]["rows"] > 0
    assert ood["default_answer"]["mean_r_reproduced"] != ood["default_answer"]["mean_r_surr"]


def test_the_ood_warning_is_chosen_among_scores_a_target_alone_gives(bundle: Path, monkeypatch: Any) -> None:
    """A score that needs the answer (ensemble spread, draws) cannot be computed by the answer-time warning, which
    then never fires: diagnose picks among the target-only scores even when another ranks failures better (the
    old code picked it and shipped a bundle whose warning was silently off)."""
    from invphys.evaluation import diagnose as dg
    from invphys.evaluation.ood import NEEDS
    from invphys.inverter import load_inverter

    real, components, marked = dg.auroc, dg.score_components, 7.0

    def answer_scores_rank_best(*args: Any, **kwargs: Any) -> Any:
        out = components(*args, **kwargs)
        out["ensemble_std"] = np.full(len(out["knn"]), marked)  # recognisable below
        return out

    def auroc(score: Any, failed: Any) -> float:
        return 1.0 if np.all(np.asarray(score) == marked) else min(float(np.nan_to_num(real(score, failed))), 0.9)

    monkeypatch.setattr(dg, "score_components", answer_scores_rank_best)
    monkeypatch.setattr(dg, "auroc", auroc)
    ood = dg.diagnose(load_inverter(bundle), draws=20).report["ood"]
    assert not NEEDS.get(ood["chosen"]) and ood["chosen"] == "knn"
    assert ood["candidates"]["ensemble_std"]["r_surr"]["fit"] == 1.0  # reported, not chosen
