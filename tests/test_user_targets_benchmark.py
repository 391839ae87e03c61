"""benchmarks/bench_user_targets.py: user-like sets scored next to a lookup over all data and the truth."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from benchmark_modules import load

QUICK_BUNDLE = "inverters/orange_peel_quick"
QUICK_STORE = "datasets/orange_peel_quick"


def test_scores_each_method_against_a_lookup_over_all_stores(tmp_path: Path) -> None:
    bench = load("bench_user_targets")
    out = tmp_path / "user_targets.json"
    assert bench.main(["--bundle", QUICK_BUNDLE, "--targets", f"quick={QUICK_STORE}", "--all-data", QUICK_STORE,
                       "--methods", "gc_ppo_vae", "--limit", "6", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["validated"] is False and report["command"] and report["device"]
    rows = report["sets"]["quick"]["methods"]
    assert set(rows) == {"gc_ppo_vae", "nearest_neighbour_all", "truth"}
    assert all(r["n"] == 6 for r in rows.values())
    # the targets are rows of the lookup's store: the lookup leaves them out (it would find each one itself)
    assert rows["nearest_neighbour_all"]["theta_error"] > 0.0
    diff = rows["gc_ppo_vae"]["vs_nearest_neighbour_all"]
    assert np.isclose(diff["mean_diff"], rows["gc_ppo_vae"]["r_mean"] - rows["nearest_neighbour_all"]["r_mean"])
    lo, hi = rows["gc_ppo_vae"]["r_ci95"]
    assert lo <= rows["gc_ppo_vae"]["r_mean"] <= hi


def test_answers_written_on_one_machine_are_scored_on_another(tmp_path: Path) -> None:
    """--answers-out writes every answer's parameters; --answers-in re-scores exactly those answers
    without answering (the GPU run needs no sbi), several files side by side under their labels."""
    bench = load("bench_user_targets")
    common = ["--bundle", QUICK_BUNDLE, "--targets", f"quick={QUICK_STORE}", "--limit", "5"]
    first, answers = tmp_path / "first.json", tmp_path / "answers.json"
    assert bench.main([*common, "--methods", "gc_ppo_vae", "--label", "a", "--answers-out", str(answers),
                       "--out", str(first)]) == 0
    saved = json.loads(answers.read_text())
    rec = saved["sets"]["quick"]["methods"]["a:gc_ppo_vae"]
    assert np.array(rec["theta"]).shape == (5, 9) and rec["answer_ms_per_target"] > 0
    other = tmp_path / "answers_b.json"
    assert bench.main([*common, "--methods", "gc_ppo_vae", "--seed", "1", "--label", "b",
                       "--answers-out", str(other), "--out", str(tmp_path / "b.json")]) == 0
    again = tmp_path / "again.json"
    assert bench.main([*common, "--answers-in", str(answers), str(other), "--all-data", QUICK_STORE,
                       "--out", str(again)]) == 0
    rows = json.loads(again.read_text())["sets"]["quick"]["methods"]
    assert set(rows) == {"a:gc_ppo_vae", "b:gc_ppo_vae", "nearest_neighbour_all", "truth"}
    before = json.loads(first.read_text())["sets"]["quick"]["methods"]["gc_ppo_vae"]
    assert rows["a:gc_ppo_vae"]["r_mean"] == before["r_mean"]  # the same parameters, the same scores
    assert rows["a:gc_ppo_vae"]["theta_error"] == before["theta_error"] and rows["truth"]["theta_error"] == 0.0
    only = tmp_path / "only.json"
    assert bench.main([*common, "--answers-in", str(answers), str(other), "--methods", "b:gc_ppo_vae",
                       "--out", str(only)]) == 0
    assert set(json.loads(only.read_text())["sets"]["quick"]["methods"]) == {"b:gc_ppo_vae", "truth"}
    # a file that is not an answers file, or a label given twice, is refused
    import pytest

    with pytest.raises(SystemExit, match="not an answers file"):
        bench.main([*common, "--answers-in", str(first), "--out", str(tmp_path / "x.json")])
    with pytest.raises(SystemExit, match="two answers files"):
        bench.main([*common, "--answers-in", str(answers), str(answers), "--out", str(tmp_path / "x.json")])


def test_held_out_rows_by_key_file_with_every_answer_per_target(tmp_path: Path) -> None:
    """``STORE@KEYFILE`` answers only the listed rows; ``--per-target-out`` keeps each target's answer and
    scores (what a failure warning is fitted on); ``--no-truth`` leaves the truth out."""
    from invphys.core.dataset import DatasetStore

    keys = [str(k) for k in DatasetStore(QUICK_STORE).arrays().keys[3:7]]
    key_file = tmp_path / "held_out.txt"
    key_file.write_text("# four rows\n" + "\n".join(keys) + "\n")
    bench = load("bench_user_targets")
    per_target, out = tmp_path / "per_target.json", tmp_path / "out.json"
    assert bench.main(["--bundle", QUICK_BUNDLE, "--targets", f"held={QUICK_STORE}@{key_file}", "--all-data",
                       QUICK_STORE, "--methods", "warm_start_vae", "--no-truth", "--per-target-out", str(per_target),
                       "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["sets"]["held"]["methods"]
    assert set(rows) == {"warm_start_vae", "nearest_neighbour_all"} and rows["warm_start_vae"]["n"] == 4
    data = json.loads(per_target.read_text())["sets"]["held"]
    assert data["keys"] == keys and np.array(data["y"]).shape == (4, 12)
    rec = data["methods"]["warm_start_vae"]
    assert np.array(rec["theta"]).shape == (4, 9) and rec["r_actual"] == [None] * 4
    assert np.isclose(np.mean(rec["r_surrogate"]), rows["warm_start_vae"]["r_mean"])


def test_pool_variants_parse_each_setting_by_its_type() -> None:
    import pytest

    bench = load("bench_user_targets")
    assert bench._pool_value("lam", "0.5") == 0.5 and bench._pool_value("moves", "8") == 8
    assert bench._pool_value("margin", "0.03") == 0.03 and bench._pool_value("rows", "all") == "all"
    assert bench._pool_value("exact", "true") is True and bench._pool_value("anchor", "0") is False
    assert bench._pool_value("extra", "npe_nsf+npe_nsf1") == ("npe_nsf", "npe_nsf1")
    with pytest.raises(SystemExit, match="unknown pool setting 'lamb'"):
        bench._pool_value("lamb", "1")


def test_a_run_cut_short_keeps_the_sets_it_finished(tmp_path: Path, monkeypatch: Any) -> None:
    """The result, answers and per-target files are written after every set: a validation stopped by a time
    limit during the second set still leaves the first set's scores (the old code wrote only at the end)."""
    bench = load("bench_user_targets")
    real, calls = bench._answers, []

    def answers_then_stop(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # what a time limit does to the second set
        return real(*args, **kwargs)

    monkeypatch.setattr(bench, "_answers", answers_then_stop)
    out, answers, per = tmp_path / "r.json", tmp_path / "a.json", tmp_path / "p.json"
    with pytest.raises(KeyboardInterrupt):
        bench.main(["--bundle", QUICK_BUNDLE, "--targets", f"one={QUICK_STORE}", f"two={QUICK_STORE}",
                    "--methods", "gc_ppo_vae", "--limit", "3", "--answers-out", str(answers),
                    "--per-target-out", str(per), "--out", str(out)])
    assert list(json.loads(out.read_text())["sets"]) == ["one"]
    assert json.loads(out.read_text())["sets"]["one"]["methods"]["gc_ppo_vae"]["n"] == 3
    assert list(json.loads(answers.read_text())["sets"]) == ["one"]
    assert list(json.loads(per.read_text())["sets"]) == ["one"]


def test_the_lookup_over_all_data_is_scored_by_its_stored_features_without_a_simulator(tmp_path: Path) -> None:
    """The lookup's answers are stored rows: their real R (``stored_rows``) is the R of the row's stored
    features against the target, computed here independently from the store (the row the lookup picks is the
    one whose features reach the highest R), with no re-simulation."""
    from invphys.core.dataset import DatasetStore
    from invphys.core.masked_recovery import masked_recovery
    from invphys.inverter import load_inverter

    bench = load("bench_user_targets")
    out = tmp_path / "out.json"
    assert bench.main(["--bundle", QUICK_BUNDLE, "--targets", f"quick={QUICK_STORE}", "--all-data", QUICK_STORE,
                       "--methods", "gc_ppo_vae", "--limit", "5", "--no-truth", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["sets"]["quick"]["methods"]
    stored = rows["nearest_neighbour_all"]["stored_rows"]
    inv = load_inverter(QUICK_BUNDLE)
    arrays = DatasetStore(QUICK_STORE).arrays(ok_only=True)
    expected = []
    for i in range(5):  # each target against every other row of the store (its own row left out)
        others = np.delete(arrays.y, i, axis=0)
        r = masked_recovery(others, arrays.y[i], inv.bundle.scales, None, inv.bundle.kappa)
        expected.append(r.max())
    assert stored["n"] == 5 and np.isclose(stored["r_mean"], np.mean(expected))
    assert np.isclose(stored["r_worst"], min(expected)) and stored["r_ci95"][0] <= stored["r_mean"]
    assert "stored_rows" not in rows["gc_ppo_vae"]  # the policy's answers are new parameters: R unknown


def test_a_bundle_pool_entry_is_answered_with_other_settings(tmp_path: Path) -> None:
    """``POOL:KEY=VALUE`` works for a bundle's own pool entry too (``pool_nsf4``): with its stored rows scored
    exactly and a margin no surrogate-scored candidate can overcome, every answer is a stored row (its real R
    known); the entry as shipped answers with its own settings, and a variant's settings win over them."""
    bench = load("bench_user_targets")
    out = tmp_path / "out.json"
    assert bench.main(["--bundle", "inverters/orange_peel_paper_all", "--targets",
                       "edge=datasets/orange_peel_paper_fresh_edge", "--methods", "pool_nsf4",
                       "pool_nsf4:exact=true,margin=0.99", "pool_nsf4:exact=false,margin=0", "--limit", "3",
                       "--no-truth", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["sets"]["edge"]["methods"]
    assert rows["pool_nsf4:exact=true,margin=0.99"]["stored_rows"]["n"] == 3
    # the variant's settings win over the entry's own (it ships exact): no answer is scored as a stored row
    assert "stored_rows" not in rows["pool_nsf4:exact=false,margin=0"]
    assert rows["pool_nsf4"]["r_surrogate_mean"] > rows["pool_nsf4:exact=true,margin=0.99"]["r_surrogate_mean"]


def test_validating_re_simulates_new_answers_but_scores_stored_rows_by_their_features(
        tmp_path: Path, monkeypatch: Any) -> None:
    """With ``--validate`` the lookup's answers (stored rows: already simulated) are not re-simulated; their
    stored features' R is their R_actual, next to the policy's re-simulated answers (the old code re-ran every
    stored row too: four runs here instead of two)."""
    from invphys.inverter.inverter import Inverter

    bench = load("bench_user_targets")
    simulated: list[str] = []
    real_validate = Inverter.validate

    def counting(self: Any, results: Any, **kwargs: Any) -> Any:
        simulated.extend(r.method for r in results)
        assert kwargs["extract_workers"] == 1   # --extract-workers reaches the validation
        return real_validate(self, results, **kwargs)

    monkeypatch.setattr(Inverter, "validate", counting)
    out, per = tmp_path / "out.json", tmp_path / "per.json"
    assert bench.main(["--bundle", QUICK_BUNDLE, "--targets", f"quick={QUICK_STORE}", "--all-data", QUICK_STORE,
                       "--methods", "gc_ppo_vae", "--limit", "2", "--no-truth", "--validate",
                       "--extract-workers", "1", "--per-target-out", str(per), "--out", str(out)]) == 0
    assert sorted(simulated) == ["gc_ppo_vae", "gc_ppo_vae"]
    quick = json.loads(out.read_text())["sets"]["quick"]
    assert quick["validate_runs"] == 2 and quick["extract_workers"] == 1 and quick["validate_s_per_run"] > 0
    rows = quick["methods"]
    lookup = rows["nearest_neighbour_all"]
    assert lookup["r_mean"] == pytest.approx(lookup["stored_rows"]["r_mean"])
    rec = json.loads(per.read_text())["sets"]["quick"]["methods"]
    assert all(r is not None for r in rec["gc_ppo_vae"]["r_actual"] + rec["nearest_neighbour_all"]["r_actual"])
    diff = rows["gc_ppo_vae"]["vs_nearest_neighbour_all"]["mean_diff"]
    assert diff == pytest.approx(rows["gc_ppo_vae"]["r_mean"] - lookup["r_mean"])
