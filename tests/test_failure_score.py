"""The answer-level failure score (invphys.evaluation.failure_score) on the shipped paper bundle (read
only): its scores depend on the target and the answer alone, the model is plain JSON numbers that rank
planted failures first, its threshold catches the recall asked for, and validated-answer files are read
strictly (training rows among them counted and left out)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from invphys.core.errors import InvphysError

PAPER = Path(__file__).resolve().parents[1] / "inverters" / "orange_peel_paper"


@pytest.fixture(scope="module")
def paper():
    from invphys.inverter.bundle import Bundle

    return Bundle(PAPER, verify=False)


def _planted(paper, n: int = 120):
    """Held-out-like targets (the bundle's test rows) with their true parameters as answers, half of them
    moved far: those 'fail'."""
    theta, y = paper.data("test")
    theta, y = np.asarray(theta[:n], dtype=np.float64), np.asarray(y[:n], dtype=np.float64)
    rng = np.random.default_rng(0)
    bad = np.arange(n) % 2 == 1
    answers = theta.copy()
    answers[bad] = np.clip(answers[bad] + rng.choice([-0.35, 0.35], size=answers[bad].shape), 0.0, 1.0)
    return y, theta, answers, bad


def test_scores_depend_on_the_target_and_the_answer_alone(paper) -> None:
    from invphys.evaluation.failure_score import SCORES, components

    y, _, answers, _ = _planted(paper, 12)
    batch = components(paper, y, answers)
    assert set(batch) == set(SCORES)
    rev = components(paper, y[::-1], answers[::-1])
    alone = components(paper, y[5:6], answers[5:6])
    for n in SCORES:
        np.testing.assert_allclose(rev[n][::-1], batch[n], rtol=0, atol=1e-12)
        np.testing.assert_allclose(alone[n][0], batch[n][5], rtol=0, atol=1e-12)
    with pytest.raises(InvphysError, match="answers have shape"):
        components(paper, y, answers[:3])


def test_a_training_row_as_target_is_scored_without_itself(paper) -> None:
    from invphys.evaluation.failure_score import K_LOCAL, local_error
    from invphys.evaluation.ood import feature_targets, knn_distance, neighbours

    y = np.asarray(paper.data("train")[1][:4], dtype=np.float64)
    t = feature_targets(paper, y)
    _, idx = neighbours(paper, t, K_LOCAL, leave_identical=True)
    assert not np.any(idx == np.arange(4)[:, None])  # its own row is never among its neighbours
    _, with_self = neighbours(paper, t, K_LOCAL)
    assert np.all(with_self[:, 0] == np.arange(4))
    assert np.all(knn_distance(paper, t, leave_identical=True) > knn_distance(paper, t))
    assert np.all(np.isfinite(local_error(paper, y))) and np.all(local_error(paper, y) > 0)


def test_the_fitted_model_is_plain_json_ranks_planted_failures_first_and_meets_its_recall(paper) -> None:
    from invphys.evaluation.failure_score import components, fit, measure, probability

    y, _, answers, bad = _planted(paper)
    comps = components(paper, y, answers)
    model = fit(comps, bad, recall=0.8, rule="recall")
    loaded = json.loads(json.dumps(model, allow_nan=False))  # strict JSON, nothing pickled
    p = probability(loaded, comps)
    np.testing.assert_allclose(p, probability(model, comps))
    assert model["calibration"]["auroc"] > 0.95 and model["calibration"]["auroc_each"]["misfit"] > 0.95
    m = measure(p, bad, model["threshold"])
    assert m["recall"] >= 0.8 and m == {k: model["calibration"][k] for k in m}
    assert measure(p, bad, np.nextafter(model["threshold"], 1.0))["recall"] < 0.8  # the largest such threshold
    with pytest.raises(InvphysError, match=">= 5 failing"):
        fit(comps, np.zeros(len(bad), dtype=bool))


def test_the_default_threshold_bounds_false_alarms_on_typical_answers(paper) -> None:
    """The ``alarms`` rule: at most 10 % - 1.5 SE of the typical calibration answers are warned, and the
    smallest such threshold (one step lower warns one more)."""
    from invphys.evaluation.failure_score import components, fit, probability, threshold

    y, _, answers, bad = _planted(paper)
    comps = components(paper, y, answers)
    model = fit(comps, bad)
    p = probability(model, comps)
    rule = model["threshold_rule"]
    assert rule["rule"] == "alarms" and 0 < rule["allowed"] < 0.10
    fires = p >= model["threshold"]
    assert fires[~bad].mean() <= rule["allowed"]
    typical = np.sort(p[~bad])
    below = typical[typical < model["threshold"]]
    assert (p[~bad] >= below.max()).mean() > rule["allowed"]  # lowering it to the next typical score is too many
    assert model["calibration"]["alarm_rate"] == fires[~bad].mean()
    with pytest.raises(InvphysError, match="unknown failure-threshold rule"):
        threshold(p, bad, "median")


def _validated(path: Path, y, truth, answers, bad, method: str = "npe_best64") -> Path:
    r = np.where(bad, 0.5, 0.95)
    path.write_text(json.dumps({"benchmark": "user_targets_per_target", "validated": True, "sets": {"heldout": {
        "keys": [f"k{i}" for i in range(len(y))], "y": y.tolist(), "truth_theta": truth.tolist(),
        "methods": {method: {"theta": answers.tolist(), "r_actual": r.tolist(), "r_surrogate": r.tolist()}}}}}))
    return path


def test_validated_answers_are_read_strictly_and_training_rows_left_out(paper, tmp_path: Path) -> None:
    from invphys.evaluation.failure_score import fit_from_file

    y, truth, answers, bad = _planted(paper, 60)
    th_train, y_train = paper.data("train")
    y = np.vstack([y, y_train[:10]])  # ten rows the bundle trained on
    truth = np.vstack([truth, th_train[:10]])
    answers = np.vstack([answers, th_train[:10]])
    bad = np.concatenate([bad, np.zeros(10, dtype=bool)])
    path = _validated(tmp_path / "v.json", y, truth, answers, bad)
    model, comps = fit_from_file(paper, f"{path}:heldout", "npe_best64")
    assert model["rows"] == {"file": "v.json", "sets": ["heldout"], "given": 70, "training_rows": 10,
                             "training_rows_used": False, "used": 60}
    assert len(comps["failed"]) == 60 and model["calibration"]["n"] == 60
    assert fit_from_file(paper, path, "npe_best64", keep_training=True)[0]["rows"]["used"] == 70
    with pytest.raises(InvphysError, match="no set named other"):
        fit_from_file(paper, f"{path}:other", "npe_best64")
    with pytest.raises(InvphysError, match="no validated answers of method 'lookup'"):
        fit_from_file(paper, path, "lookup")
    (tmp_path / "bad.json").write_text(json.dumps({"sets": {}}))
    with pytest.raises(InvphysError, match="not a per-target file of validated answers"):
        fit_from_file(paper, tmp_path / "bad.json", "npe_best64")
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(InvphysError):
        fit_from_file(paper, tmp_path / "broken.json", "npe_best64")


def test_the_fitting_script_measures_other_sets_and_stores_the_model_in_the_bundle(paper, tmp_path: Path) -> None:
    """benchmarks/fit_failure_warning.py on a private copy of the paper bundle: fitted on one file's rows,
    measured on another's, stored (the bundle still verifies and its answers' warning reads it)."""
    import importlib.util
    import shutil

    from invphys.inverter.bundle import Bundle
    from invphys.inverter.diagnosed import failure_score

    spec = importlib.util.spec_from_file_location("fit_failure_warning", PAPER.parents[1] / "benchmarks"
                                                  / "fit_failure_warning.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    root = tmp_path / "bundle"
    shutil.copytree(PAPER, root)
    y, truth, answers, bad = _planted(paper, 120)
    cal = _validated(tmp_path / "cal.json", y[:80], truth[:80], answers[:80], bad[:80])
    rep = _validated(tmp_path / "rep.json", y[80:], truth[80:], answers[80:], bad[80:])
    out = tmp_path / "result.json"
    assert script.main(["--bundle", str(root), "--calibration", f"{cal}:heldout", "--report", str(rep),
                        "--out", str(out), "--write"]) == 0
    result = json.loads(out.read_text())
    assert result["model"]["rows"]["used"] == 80 and result["sets"]["heldout"]["warning"]["n"] == 40
    assert result["sets"]["heldout"]["warning"]["auroc"] > 0.9  # planted failures, rows it never saw
    b = Bundle(root)  # re-hashed: verifies
    stored = json.loads((root / "diagnostics" / "calibration.json").read_text())["failure"]
    assert stored["threshold"] == result["model"]["threshold"]
    given = np.ones(12, dtype=bool)
    assert bad[81] and not bad[80]
    assert failure_score(b, y[81], given, answers[81]) > failure_score(b, y[80], given, answers[80])
    assert "Failure warning (answer-level" in (root / "README.md").read_text()
