"""The Python API: load_inverter(path).invert(target) -> InversionResult, top-k, refine, validate."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_inverter_support import toy_run


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    return toy_run(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def inv(run):
    import invphys

    return invphys.load_inverter(run / "inverter")


@pytest.fixture(scope="module")
def target(inv):
    _, y = inv.bundle.data("test")
    return dict(zip(inv.feature_names, map(float, y[0]), strict=True))


def test_result_by_name_with_units(inv, target) -> None:
    from invphys.core.masked_recovery import masked_recovery

    res = inv.invert(target)
    assert res.method == inv.default_method and res.evaluations == 8
    assert list(res.parameters) == ["k", "c", "m"]
    for name, value in res.parameters.items():
        p = inv.parameter_space[name]
        assert p.low <= value <= p.high
    assert np.all((res.theta >= 0) & (res.theta <= 1))
    assert inv.parameter_space.denormalize(res.theta) == pytest.approx(list(res.parameters.values()))
    assert list(res.predicted) == list(inv.feature_names) and max(res.uncertainty.values()) > 0
    y = np.array(list(res.predicted.values()))
    assert res.r_surrogate == pytest.approx(float(masked_recovery(y, list(target.values()), inv.bundle.scales)))
    d = json.loads(json.dumps(res.to_dict()))
    assert d["candidates"][0]["parameters"]["m"]["unit"] == "kg"
    # the same target as an array in the bundle's feature order
    assert inv.invert(np.array(list(target.values()))).theta == pytest.approx(res.theta)


def test_top_k_candidates_are_diverse_and_ranked(inv, target) -> None:
    from invphys.inverter.inverter import MIN_DISTANCE

    res = inv.invert(target, top_k=3)
    assert len(res.candidates) == 3
    scores = [c.r_surrogate for c in res.candidates]
    assert scores == sorted(scores, reverse=True) and scores[0] >= inv.invert(target).r_surrogate - 1e-12
    t = np.array([c.theta for c in res.candidates])
    dist = [np.linalg.norm(t[i] - t[j]) / np.sqrt(3) for i in range(3) for j in range(i)]
    assert min(dist) >= MIN_DISTANCE
    assert set(res.spread()) == {"k", "c", "m"} and "spread" in res.to_dict()


def test_refine_spends_its_budget_and_never_loses(inv, target) -> None:
    base = inv.invert(target)
    refined = inv.invert(target, refine=60)
    assert refined.evaluations == base.evaluations + 60
    assert refined.r_surrogate >= base.r_surrogate


def test_every_bundle_method_a_registry_optimiser_and_a_baseline(inv, target) -> None:
    for method in [*inv.methods, "cma_es", "nearest_neighbour"]:  # a dataset baseline fits on the bundle's rows
        res = inv.invert(target, method=method, seed=1)
        assert res.method == method and 0 < res.r_surrogate <= 1, method
    assert inv.invert(target, method="cma").evaluations == 200
    with pytest.raises(Exception, match=r"needs training first .* trained policies: gc, gc_flow"):
        inv.invert(target, method="gc_ppo")  # untrained: the registry's class, not the bundle's policy


def test_partial_targets_score_only_given_features(inv, target) -> None:
    from invphys.core.masked_recovery import masked_recovery

    given = {k: target[k] for k in ("peak_abs", "log_decay")}
    with pytest.raises(Exception, match="missing feature"):
        inv.invert(given)
    res = inv.invert(given, partial=True)
    mask = np.array([n in given for n in inv.feature_names])
    y = np.array(list(res.predicted.values()))
    full = np.array([target[n] for n in inv.feature_names])
    assert res.r_surrogate == pytest.approx(float(masked_recovery(y[mask], full[mask], inv.bundle.scales[mask])))


def test_validate_matches_the_validate_stage(run, inv) -> None:
    rows = [r for r in json.loads((run / "validate" / "validation.json").read_text()) if r["problem"] == "target"]
    feats = json.loads((run / "invert" / "targets.json").read_text())["features"]
    assert rows
    results = [inv.evaluate(theta=r["theta"], target=feats[r["target_index"]]) for r in rows]
    runs: list[int] = []
    inv.validate(results, on_run=runs.append)
    assert len(runs) == len(rows)
    for r, res in zip(rows, results, strict=True):
        assert res.r_actual == pytest.approx(r["r_actual"], abs=1e-9)
        assert res.best.gap == pytest.approx(res.r_surrogate - r["r_actual"], abs=1e-9)
    with pytest.raises(Exception, match="simulator options do not fit"):
        inv.validate(results[0], overrides={"n_frames": 0})


def test_chunked_rollouts_answer_like_one_batch(inv, monkeypatch) -> None:
    """Large batches roll in chunks of rows (for the CPU cache); the answers must not change."""
    from invphys.inverter import policy

    _, y = inv.bundle.data("test")
    ys = np.resize(y, (23, y.shape[1]))
    whole = inv.invert_array(ys)
    monkeypatch.setattr(policy, "CHUNK_ROWS", 5)
    calls = []
    inner = policy.PolicyRunner._rollout
    monkeypatch.setattr(policy.PolicyRunner, "_rollout", lambda self, g, *a: calls.append(len(g)) or inner(self, g, *a))
    chunked = inv.invert_array(ys)
    assert calls == [5, 5, 5, 5, 3]
    assert chunked.shape == whole.shape == (23, 3)
    np.testing.assert_allclose(chunked, whole, atol=1e-5)
    # stochastic rollouts (top-k) are chunked too and still give ranked, diverse candidates
    res = inv.invert_many(ys[:4], top_k=2)
    assert all(len(r.candidates) == 2 for r in res)


def test_one_polish_settings_model_for_the_api_the_cli_and_the_spec() -> None:
    """Polish settings were checked in three places with three sets of rules; one model checks them all."""
    from invphys.core.errors import InvphysError
    from invphys.core.spec import PolishSection
    from invphys.inverter.inverter import check_polish
    from invphys.inverter.settings import PolishSettings

    assert set(PolishSection.model_fields) == set(PolishSettings.model_fields)
    assert PolishSettings.checked(**PolishSection().model_dump()).sigma0 == PolishSection().sigma0
    for kw, msg in (({"sigma0": float("nan")}, "sigma0 must be a finite number"), ({"popsize": True}, "whole number"),
                    ({"below": 1.5}, "below must be in (0, 1]"), ({"budget": -1}, "budget must be >= 0")):
        with pytest.raises(InvphysError, match=msg.replace("(", r"\(").replace(")", r"\)").replace("]", r"\]")):
            PolishSettings.checked(**kw)
    with pytest.raises(InvphysError, match="confirm_candidates must be >= 1"):
        check_polish(4, 8, 0.1, 1.0, 0, 0)


def test_a_python_version_note_only_where_it_can_matter(run, tmp_path, recwarn) -> None:
    """Every part of the toy bundle loads from arrays: another Python cannot change an answer, so loading
    warns nothing (before, every load warned that the bundle was written with another Python)."""
    import shutil

    import yaml

    import invphys

    root = tmp_path / "bundle"
    shutil.copytree(run / "inverter", root)
    m = yaml.safe_load((root / "manifest.yaml").read_text())
    m["system_info"]["python"] = "2.7.18"
    (root / "manifest.yaml").write_text(yaml.safe_dump(m, sort_keys=False))
    inv = invphys.load_inverter(root)
    assert not [w for w in recwarn if "Python" in str(w.message)]
    assert not [n for n in inv.notes if "Python" in n]
