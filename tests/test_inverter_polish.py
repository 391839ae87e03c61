"""Inverter.polish and `invphys invert --polish`: CMA-ES on the real (toy) simulator from validated answers."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from test_inverter_support import toy_bundle_fixture, toy_inverter_fixture  # noqa: F401 (fixtures bundle, inv)
from typer.testing import CliRunner

from invphys.core.errors import InvphysError


@pytest.fixture
def sim_rows(monkeypatch):
    """Simulator rows run so far (counts every real simulation, validation and polish alike)."""
    from test_dataset_toy import ToyOscillator

    rows = [0]
    inner = ToyOscillator.simulate

    def counted(self, params, on_result=None):
        rows[0] += len(np.atleast_2d(params))
        return inner(self, params, on_result)

    monkeypatch.setattr(ToyOscillator, "simulate", counted)
    return rows


def _check_scores(inv, res) -> None:
    """Every simulated candidate's R_actual is the masked R of its features; gap = R_surr - R_actual."""
    from invphys.core.masked_recovery import masked_recovery

    b = inv.bundle
    for c in res.candidates:
        r = float(masked_recovery(c.actual, res.target, b.scales, res.mask, b.kappa))
        assert c.r_actual == pytest.approx(r, abs=1e-12) and c.gap == pytest.approx(c.r_surrogate - c.r_actual)


def test_polish_never_worse_improves_and_counts_runs(inv, sim_rows) -> None:
    _, y = inv.bundle.data("test")
    res = inv.invert_many(y[:6], top_k=2)
    inv.validate(res)
    r0 = np.array([max(c.r_actual for c in r.candidates) for r in res])
    below = float(np.sort(r0)[4])  # the two best targets are left alone
    before = [[c.source for c in r.candidates] for r in res]
    sim_rows[0] = 0
    inv.polish(res, budget=16, below=below)
    chosen = r0 < below
    assert chosen.sum() == 4 and sim_rows[0] == 4 * 16  # nothing validated twice, 16 new runs per polished target
    for r, start, ch, names in zip(res, r0, chosen, before, strict=True):
        p = r.polish
        assert p["polished"] == ch and p["runs"] == (16 if ch else 0) and p["start_r_actual"] == start
        assert r.r_actual >= start and p["r_actual"] == r.r_actual and p["device"] == "cpu"
        if not ch:  # the same candidates, the best simulated one first (the answer polish started from)
            assert sorted(c.source for c in r.candidates) == sorted(names)
            assert r.best.r_actual == max(c.r_actual for c in r.candidates)
        elif p["improved"]:
            assert r.best.source == f"{p['start_source']} + polish" and len(r.candidates) == 3
            assert r.best.predicted == pytest.approx(inv.bundle.surrogate.predict_with_uncertainty(
                r.best.theta[None, :])[0][0])
        _check_scores(inv, r)
    gains = np.array([r.r_actual for r in res]) - r0
    assert gains[chosen].max() > 0.02 and np.all(gains[~chosen] == 0)
    call = res[0].polish["call"]
    assert call["runs"] == 64 and call["replayed_runs"] == 0 and call["polished"] == 4
    d = json.loads(json.dumps(res[0].to_dict()))
    assert d["polish"]["runs"] == res[0].polish["runs"]


def test_partial_target_is_polished_on_its_given_features(inv, sim_rows) -> None:
    from invphys.core.objectives import recovery_reward

    _, y = inv.bundle.data("test")
    given = dict(list(zip(inv.feature_names, map(float, y[1]), strict=True))[:3])
    res = inv.invert(given, partial=True)
    inv.polish(res, budget=16)
    assert sim_rows[0] == 1 + 16  # the start validated, then polished
    assert res.polish["improved"] and res.r_actual > res.polish["start_r_actual"] + 0.01
    _check_scores(inv, res)
    # R over every feature (the missing ones as the true row's values) is another number
    full = float(recovery_reward(res.best.actual, y[1], inv.bundle.scales, inv.bundle.kappa))
    assert abs(full - res.r_actual) > 1e-3


def test_the_log_replays_a_polish(inv, sim_rows, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    base = inv.validate(inv.invert_many(y[:3]))
    log = tmp_path / "polish.npz"
    first = inv.polish(copy.deepcopy(base), budget=16, log=log, batch_size=5)
    assert sim_rows[0] == 3 + 48 and log.is_file()
    sim_rows[0] = 0
    again = inv.polish(copy.deepcopy(base), budget=16, log=log, batch_size=5)
    assert sim_rows[0] == 0 and again[0].polish["call"]["replayed_runs"] == 48
    for a, b in zip(first, again, strict=True):
        assert np.array_equal(a.theta, b.theta) and a.r_actual == b.r_actual and b.polish["runs"] == 16
    more = inv.polish(copy.deepcopy(base), budget=24, log=log, batch_size=5)  # a larger budget: only the rest runs
    assert sim_rows[0] == 24 and more[0].polish["call"]["replayed_runs"] == 48
    assert all(m.r_actual >= a.r_actual for m, a in zip(more, first, strict=True))
    sim_rows[0] = 0
    kept = log.read_bytes()
    with pytest.raises(InvphysError, match="made for another bundle, target set or polish settings"):
        inv.polish(copy.deepcopy(base), budget=16, log=log, batch_size=5, sigma0=0.02)  # other settings: refused
    assert log.read_bytes() == kept and sim_rows[0] == 0  # refused before the polish simulated anything
    inv.polish(copy.deepcopy(base), budget=16, log=tmp_path / "other.npz", batch_size=5, sigma0=0.02)  # afresh
    assert sim_rows[0] == 48 and log.read_bytes() == kept


def test_the_log_never_overwrites_a_file_that_is_not_a_polish_log(inv, sim_rows, tmp_path) -> None:
    """A user's CSV named as the log is refused and kept byte for byte (it became an npz before); so is a
    truncated log (its batches cost simulator time: it is not silently replaced)."""
    _, y = inv.bundle.data("test")
    base = inv.validate(inv.invert_many(y[:2]))
    sim_rows[0] = 0
    mine = tmp_path / "targets.csv"
    mine.write_text("a,b\n1,2\n")
    with pytest.raises(InvphysError, match="not a polish log written by invphys; refusing to overwrite it"):
        inv.polish(copy.deepcopy(base), budget=8, log=mine)
    assert mine.read_text() == "a,b\n1,2\n" and sim_rows[0] == 0
    log = tmp_path / "polish.npz"
    inv.polish(copy.deepcopy(base), budget=8, log=log)
    good = log.read_bytes()
    log.write_bytes(good[: len(good) // 2])
    with pytest.raises(InvphysError, match=r"polish log .*polish\.npz.*truncated or corrupt"):
        inv.polish(copy.deepcopy(base), budget=8, log=log)
    assert log.read_bytes() == good[: len(good) // 2]


def test_check_polish_log_refuses_bad_places_before_anything_runs(tmp_path) -> None:
    import os

    from invphys.evaluators.polish import check_polish_log

    (tmp_path / "file").write_text("x")
    for path, needle in ((tmp_path / "file" / "p.npz", "is a file, not a directory"),
                         (tmp_path / "file" / "deeper" / "p.npz", "is a file, not a directory"),
                         (tmp_path, "it is a directory"),
                         (tmp_path / "file", "not a polish log written by invphys")):
        with pytest.raises(InvphysError, match=needle):
            check_polish_log(path)
    assert check_polish_log(tmp_path / "new" / "dir" / "p.npz") == [] and not (tmp_path / "new").exists()
    os.symlink(tmp_path / "file", tmp_path / "link.npz")
    with pytest.raises(InvphysError, match="symbolic link"):
        check_polish_log(tmp_path / "link.npz")
    os.mkfifo(tmp_path / "fifo.npz")
    with pytest.raises(InvphysError, match="not a regular file"):
        check_polish_log(tmp_path / "fifo.npz")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        with pytest.raises(InvphysError, match="cannot write in"):
            check_polish_log(ro / "p.npz")


def test_bad_settings_raise(inv) -> None:
    res = inv.evaluate(theta=[0.5, 0.5, 0.5], target=inv.bundle.data("test")[1][0])
    for kw, msg in (({"budget": -1}, "budget"), ({"popsize": 1}, "popsize"), ({"sigma0": 0.0}, "sigma0"),
                    ({"below": 0.0}, "below"), ({"below": 1.5}, "below")):
        with pytest.raises(InvphysError, match=msg):
            inv.polish(res, **kw)


def _invoke(*args: str):
    from invphys.cli import app

    return CliRunner().invoke(app, list(args))


def test_cli_polish_json_and_bad_values(inv, bundle, tmp_path, monkeypatch) -> None:
    _, y = inv.bundle.data("test")
    feats = [a for n, v in zip(inv.feature_names, y[2], strict=True) for a in ("--feature", f"{n}={v}")]
    monkeypatch.chdir(tmp_path)
    log = tmp_path / "logs" / "p.npz"
    res = _invoke("invert", str(bundle), *feats, "--polish", "16", "--polish-popsize", "4", "--polish-log", str(log),
                  "--sim-batch", "3", "--json")
    assert res.exit_code == 0, res.output
    with np.load(log) as z:  # --sim-batch: the polish simulated (and logged) at most 3 rows per call
        assert {m["runs"] for m in json.loads(str(z["meta"]))} <= {1, 2, 3}
    out = json.loads(res.stdout)["results"][0]
    p = out["polish"]
    assert p["runs"] == 16 and p["settings"] == {"budget": 16, "popsize": 4, "sigma0": 0.012, "below": 1.0, "seed": 0}
    assert out["candidates"][0]["r_actual"] == p["r_actual"] >= p["start_r_actual"]
    assert f"R_actual {p['start_r_actual']:.3f} -> {p['r_actual']:.3f} (16 simulator runs" in res.stderr
    assert sorted(str(f.relative_to(tmp_path)) for f in tmp_path.rglob("*")) == ["logs", "logs/p.npz"]
    for args, needle in ((["--polish", "-1"], "--polish must be >= 0"),
                         (["--polish", "4", "--polish-sigma", "0"], "--polish-sigma must be > 0"),
                         (["--polish", "4", "--polish-below", "1.5"], "--polish-below must be in (0, 1]"),
                         (["--polish", "4", "--polish-below", "0"], "--polish-below must be in (0, 1]"),
                         (["--polish", "4", "--polish-popsize", "1"], "--polish-popsize must be >= 2"),
                         (["--polish-sigma", "0.1"], "needs --polish")):
        bad = _invoke("invert", str(bundle), *feats, *args)
        lines = [ln for ln in bad.output.strip().splitlines() if ln.strip()]
        assert bad.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error:"), bad.output
        assert needle in lines[0], lines[0]


def test_cli_polish_log_keeps_a_users_file_and_refuses_bad_places(inv, bundle, tmp_path, monkeypatch) -> None:
    """`--polish-log targets.csv` turned the user's CSV into an npz (exit 0); a log under a file or a
    truncated log was an internal error. Now: exit 2, one line naming the file, the file byte-identical."""
    _, y = inv.bundle.data("test")
    feats = [a for n, v in zip(inv.feature_names, y[2], strict=True) for a in ("--feature", f"{n}={v}")]
    monkeypatch.chdir(tmp_path)
    mine = tmp_path / "targets.csv"
    mine.write_bytes(b"a,b\n1,2\n")
    (tmp_path / "log.npz").write_bytes(b"PK\x03\x04 half an archive")
    for log, needle in ((mine, "not a polish log written by invphys"), (mine / "p.npz", "is a file, not a directory"),
                        (tmp_path / "log.npz", "truncated or corrupt")):
        bad = _invoke("invert", str(bundle), *feats, "--polish", "4", "--polish-popsize", "4", "--polish-log", str(log))
        errors = [ln for ln in bad.output.splitlines() if ln.startswith("error:")]  # (after progress bars, if any)
        assert bad.exit_code == 2 and len(errors) == 1 and "Traceback" not in bad.output, bad.output
        assert needle in errors[0] and "polish log" in errors[0], errors[0]
    assert mine.read_bytes() == b"a,b\n1,2\n" and (tmp_path / "log.npz").read_bytes() == b"PK\x03\x04 half an archive"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.npz", "targets.csv"]


# -- confirm: re-simulate the best candidates and answer with the best mean R ------------------------------
@pytest.fixture
def chaotic(monkeypatch):
    """The toy simulator made slightly chaotic (each run's stiffness is jittered by its own draw, like a
    GPU run of a chaotic simulator), counting rows; ``state["kill_after"]``: rows before a KeyboardInterrupt."""
    from test_dataset_toy import ToyOscillator

    state = {"rows": 0, "rng": np.random.default_rng(5), "jitter": 0.02, "kill_after": None}
    inner = ToyOscillator.simulate

    def jittered(self, params, on_result=None):
        p = np.array(np.atleast_2d(params), dtype=np.float64)
        if state["kill_after"] is not None and state["rows"] + len(p) > state["kill_after"]:
            raise KeyboardInterrupt("killed")
        state["rows"] += len(p)
        p[:, 0] *= np.exp(state["jitter"] * state["rng"].standard_normal(len(p)))
        return inner(self, np.clip(p, 1.0, 1e4), on_result)

    monkeypatch.setattr(ToyOscillator, "simulate", jittered)
    return state


def test_confirm_answers_with_the_best_mean_candidate_and_records_its_runs(inv, chaotic) -> None:
    from invphys.core.masked_recovery import masked_recovery

    _, y = inv.bundle.data("test")
    base = inv.validate(inv.invert_many(y[:6]))
    r0 = np.array([r.r_actual for r in base])
    below = float(np.sort(r0)[4])  # the best target is not polished: its answer alone is confirmed
    chaotic.update(rows=0, rng=np.random.default_rng(5))
    plain = inv.polish(copy.deepcopy(base), budget=16, below=below, seed=2)
    chaotic.update(rows=0, rng=np.random.default_rng(5))  # the same jitter again: the same search
    res = inv.polish(copy.deepcopy(base), budget=16, below=below, seed=2, confirm=3, confirm_candidates=3)
    chosen = r0 < below
    assert chaotic["rows"] == chosen.sum() * (16 + 3 * 3) + (~chosen).sum() * 3
    changed = 0
    for p0, r, ch in zip(plain, res, chosen, strict=True):
        c = r.polish["confirm"]
        assert r.polish["settings"] == {"budget": 16, "popsize": 8, "sigma0": 0.012, "below": below, "seed": 2,
                                        "confirm": 3, "confirm_candidates": 3}
        assert c["candidates"] == (3 if ch else 1) and c["repeats"] == 3 and c["runs"] == 3 * c["candidates"]
        assert r.polish["runs"] == (16 if ch else 0) + c["runs"]
        assert c["r_selected"] == p0.r_actual and c["selected_theta"] == p0.theta.tolist()  # the search is unchanged
        assert c["candidate_r_selected"][0] == c["r_selected"]
        runs = np.array(c["run_r"])
        assert runs.shape == (c["candidates"], 3) and np.all((runs > 0) & (runs <= 1))
        assert len({round(v, 12) for v in runs.ravel()}) > 1  # re-runs of a chaotic simulator differ
        assert np.abs(runs - np.array(c["candidate_r_selected"])[:, None]).max() < 0.05  # ... but only a little
        means = runs.mean(axis=1)
        assert c["candidate_r_mean"] == pytest.approx(means.tolist(), abs=1e-12)
        assert c["pick"] == int(np.argmax(means)) and c["changed"] == (c["pick"] > 0)
        assert r.r_actual == c["r_confirmed"] == r.polish["r_actual"] == pytest.approx(means.max(), abs=1e-12)
        assert r.best.gap == pytest.approx(r.best.r_surrogate - r.r_actual)
        # the answer's features are those of the run that found it (its R: the candidate's selecting R)
        sel = float(masked_recovery(r.best.actual, r.target, inv.bundle.scales, r.mask, inv.bundle.kappa))
        assert sel == pytest.approx(c["candidate_r_selected"][c["pick"]], abs=1e-12)
        if c["changed"]:
            changed += 1
            assert not np.array_equal(r.theta, p0.theta) and means[c["pick"]] > means[0]
        else:
            assert np.array_equal(r.theta, p0.theta)
    assert changed >= 1  # with this jitter, best-of-N and best mean disagree somewhere
    assert np.mean([c.polish["confirm"]["r_confirmed"] for c in res]) < np.mean([p.r_actual for p in plain])
    json.dumps(res[0].to_dict(), allow_nan=False)


def test_confirm_off_leaves_the_polish_as_it_was_and_its_log_replays(inv, sim_rows, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    base = inv.validate(inv.invert_many(y[:3]))
    log = tmp_path / "polish.npz"
    plain = inv.polish(copy.deepcopy(base), budget=8, log=log, batch_size=5)
    off = inv.polish(copy.deepcopy(base), budget=8, log=log, batch_size=5, confirm=0, confirm_candidates=2)
    assert [r.to_dict() | {"polish": None} for r in off] == [r.to_dict() | {"polish": None} for r in plain]
    for a, b in zip(plain, off, strict=True):
        assert "confirm" not in b.polish and set(b.polish) == set(a.polish)
        assert b.polish["settings"] == {"budget": 8, "popsize": 8, "sigma0": 0.012, "below": 1.0, "seed": 0}
    sim_rows[0] = 0  # a log made without confirm: its search replays, only the confirmation is simulated
    on = inv.polish(copy.deepcopy(base), budget=8, log=log, batch_size=5, confirm=2, confirm_candidates=2)
    assert sim_rows[0] == 3 * 2 * 2 and on[0].polish["call"]["replayed_runs"] == 3 * 8
    for a, b in zip(plain, on, strict=True):  # the toy is deterministic: re-runs reproduce, nothing changes
        c = b.polish["confirm"]
        assert c["r_selected"] == a.r_actual and c["r_confirmed"] == pytest.approx(a.r_actual, abs=1e-12)
        assert not c["changed"] and np.array_equal(a.theta, b.theta)


def test_a_killed_confirm_resumes_from_the_log(inv, chaotic, tmp_path) -> None:
    _, y = inv.bundle.data("test")
    base = inv.validate(inv.invert_many(y[:3]))
    log = tmp_path / "polish.npz"
    total = 3 * 8 + 3 * 2 * 3  # the search, then 2 candidates x 3 re-runs per target
    chaotic.update(rows=0, kill_after=3 * 8 + 10)  # killed in the confirmation (chunks of 5: 10 rows logged)
    with pytest.raises(KeyboardInterrupt):
        inv.polish(copy.deepcopy(base), budget=8, log=log, batch_size=5, confirm=3, confirm_candidates=2)
    chaotic.update(rows=0, kill_after=None)
    first = inv.polish(copy.deepcopy(base), budget=8, log=log, batch_size=5, confirm=3, confirm_candidates=2)
    assert chaotic["rows"] == total - (3 * 8 + 10) and first[0].polish["call"]["replayed_runs"] == 3 * 8 + 10
    chaotic["rows"] = 0
    again = inv.polish(copy.deepcopy(base), budget=8, log=log, batch_size=5, confirm=3, confirm_candidates=2)
    assert chaotic["rows"] == 0 and again[0].polish["call"]["replayed_runs"] == total
    for a, b in zip(first, again, strict=True):
        assert a.polish["confirm"] == b.polish["confirm"] and np.array_equal(a.theta, b.theta)
        assert a.r_actual == b.r_actual and a.polish["runs"] == b.polish["runs"] == 8 + 6


def test_cli_polish_confirm_and_its_bad_values(inv, bundle, tmp_path, monkeypatch) -> None:
    from invphys.core.errors import InvphysError

    _, y = inv.bundle.data("test")
    feats = [a for n, v in zip(inv.feature_names, y[2], strict=True) for a in ("--feature", f"{n}={v}")]
    monkeypatch.chdir(tmp_path)
    res = _invoke("invert", str(bundle), *feats, "--polish", "8", "--polish-confirm", "2",
                  "--polish-confirm-candidates", "3", "--json")
    assert res.exit_code == 0, res.output
    p = json.loads(res.stdout)["results"][0]["polish"]
    c = p["confirm"]
    assert p["settings"]["confirm"] == 2 and p["settings"]["confirm_candidates"] == 3
    assert c["candidates"] == 3 and c["runs"] == 6 and p["runs"] == 8 + 6 and len(c["run_r"]) == 3
    assert f"confirm {inv.invert(dict(zip(inv.feature_names, map(float, y[2]), strict=True))).label}" in res.stderr
    assert "(mean of 2 re-runs; candidate" in res.stderr
    for args, needle in ((["--polish", "4", "--polish-confirm", "-1"], "--polish-confirm must be >= 0"),
                         (["--polish", "4", "--polish-confirm", "2", "--polish-confirm-candidates", "0"],
                          "--polish-confirm-candidates must be >= 1"),
                         (["--polish", "4", "--polish-confirm-candidates", "2"], "needs --polish-confirm"),
                         (["--polish-confirm", "2"], "needs --polish")):
        bad = _invoke("invert", str(bundle), *feats, *args)
        lines = [ln for ln in bad.output.strip().splitlines() if ln.strip()]
        assert bad.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error:"), bad.output
        assert needle in lines[0], lines[0]
    r = inv.evaluate(theta=[0.5, 0.5, 0.5], target=y[0])
    for kw, msg in (({"confirm": -1}, "confirm"), ({"confirm": 1.5}, "confirm"),
                    ({"confirm": 1, "confirm_candidates": 0}, "confirm_candidates")):
        with pytest.raises(InvphysError, match=msg):
            inv.polish(r, **kw)


# -- seeding: a target's polish depends on the target, never on its place in the file -----------------------
def _target_file(inv, rows, path):
    path.write_text(json.dumps([dict(zip(inv.feature_names, map(float, r), strict=True)) for r in rows]))
    return path


def test_cli_polish_answers_do_not_depend_on_the_target_order(inv, bundle, tmp_path, monkeypatch) -> None:
    """Each target's CMA-ES was seeded by its position (seed + t) and all drew from cma's one global random
    state: a reversed file got other polished answers. Now each target's search is seeded from its values."""
    _, y = inv.bundle.data("test")
    rows = y[:4]
    monkeypatch.chdir(tmp_path)
    answers = []
    for name, order in (("fwd.json", rows), ("rev.json", rows[::-1])):
        f = _target_file(inv, order, tmp_path / name)
        res = _invoke("invert", str(bundle), "--target", str(f), "--polish", "12", "--polish-popsize", "4", "--json")
        assert res.exit_code == 0, res.output
        got = [(r["candidates"][0]["theta"], r["polish"]["r_actual"], r["polish"]["improved"])
               for r in json.loads(res.stdout)["results"]]
        answers.append(got if name == "fwd.json" else got[::-1])
    assert any(imp for _, _, imp in answers[0])  # the polish moved some answers
    for (ta, ra, ia), (tb, rb, ib) in zip(*answers, strict=True):
        assert ta == tb and ra == rb and ia == ib


def test_polish_of_a_target_alone_equals_its_polish_among_others(inv) -> None:
    _, y = inv.bundle.data("test")
    many = inv.polish(inv.validate(inv.invert_many(y[:3])), budget=12, popsize=4)
    alone = inv.polish(inv.validate(inv.invert_many(y[2:3])), budget=12, popsize=4)
    assert np.array_equal(many[2].theta, alone[0].theta) and many[2].r_actual == alone[0].r_actual


def test_a_log_of_the_position_seeded_polish_is_refused(inv, bundle, tmp_path, monkeypatch) -> None:
    """A log written before per-target seeding holds other searches' runs: refused with one error line
    (exit 2), kept byte for byte, never replayed into the new searches."""
    import invphys.inverter.simulate as simulate

    _, y = inv.bundle.data("test")
    f = _target_file(inv, y[:2], tmp_path / "t.json")
    log = tmp_path / "old.npz"
    real = simulate.polish_key
    monkeypatch.setattr(simulate, "polish_key", lambda *a, **k: real(*a, **{**k, "legacy": True}))
    args = ["invert", str(bundle), "--target", str(f), "--polish", "8", "--polish-popsize", "4", "--polish-log", str(log)]
    assert _invoke(*args).exit_code == 0 and log.is_file()  # a log as the older invphys keyed it
    monkeypatch.setattr(simulate, "polish_key", real)
    kept = log.read_bytes()
    bad = _invoke(*args)
    errors = [ln for ln in bad.output.splitlines() if ln.startswith("error:")]
    assert bad.exit_code == 2 and len(errors) == 1 and "Traceback" not in bad.output, bad.output
    assert "older invphys" in errors[0] and "position" in errors[0] and str(log.name) in errors[0]
    assert log.read_bytes() == kept
