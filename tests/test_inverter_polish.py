"""Inverter.polish and `invphys invert --polish`: CMA-ES on the real (toy) simulator from validated answers."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from test_inverter_support import toy_run
from typer.testing import CliRunner


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return toy_run(tmp_path_factory.getbasetemp()) / "inverter"


@pytest.fixture(scope="module")
def inv(bundle):
    import invphys

    return invphys.load_inverter(bundle)


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
    from invphys.inverter.objective import masked_recovery

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
        if not ch:
            assert [c.source for c in r.candidates] == names  # untouched
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
    inv.polish(copy.deepcopy(base), budget=16, log=log, batch_size=5, sigma0=0.02)  # other settings: afresh
    assert sim_rows[0] == 48


def test_bad_settings_raise(inv) -> None:
    from invphys.core.errors import InvphysError

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
