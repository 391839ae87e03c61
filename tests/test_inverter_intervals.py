"""Every answer says how sure it is: posterior intervals in the box, identifiability, bounds, or posterior none."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_inverter_support import paper_inverter


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    return paper_inverter(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="module")
def y(inv):
    return inv.bundle.data("test")[1]


def test_posterior_answer_has_intervals_identifiability_and_draws_in_the_box(inv, y) -> None:
    r = inv.invert(y[0], seed=0, level=0.9)
    assert r.posterior == "posterior"
    u = r.parameter_uncertainty
    assert u.draws.shape == (256, 9) and u.draws.min() >= 0 and u.draws.max() <= 1 and u.clipped == 0
    assert 0 <= u.outside_fraction < 1
    wide, narrow = r.interval(0.9), r.interval(0.5)
    for name, p in zip(inv.parameter_names, inv.parameter_space.parameters, strict=True):
        lo, med, hi = wide[name]
        assert p.low <= lo <= narrow[name][0] <= med <= narrow[name][2] <= hi <= p.high
        assert r.samples[name].shape == (256,)
    # the four parameters the 12 features do not pin (issue 48) are marked, the others identified
    ident = r.identified
    assert [n for n, ok in ident.items() if not ok] == ["eta_s", "r_s", "eta_i", "r_i"]
    d = json.loads(json.dumps(r.to_dict()))
    assert d["posterior"]["parameters"]["eta_s"]["identified"] is False and d["posterior"]["level"] == 0.9
    assert any("not identified" in w and "eta_s" in w for w in r.warnings)


def test_point_methods_say_posterior_none_and_a_lookup_gives_its_rows(inv, y) -> None:
    from invphys.core.errors import InvphysError

    r = inv.invert(y[0], method="gc_ppo_vae")
    assert r.posterior == "none" and r.samples is None and r.identified is None
    assert r.to_dict()["posterior"] is None
    with pytest.raises(InvphysError, match="no draws"):
        r.interval()
    lk = inv.invert(y[0], method="lookup")
    assert lk.posterior == "neighbours" and lk.to_dict()["posterior"] is None
    assert lk.to_dict()["neighbours"]["draws"] == 20


def test_partial_target_warns_and_its_posterior_stays_wide(inv, y) -> None:
    r = inv.invert({inv.feature_names[0]: float(y[0][0])}, partial=True)
    assert any("gives 1 features for 9 parameters" in w for w in r.warnings)
    assert any("near the prior" in w for w in r.warnings)
    assert r.parameter_uncertainty.completions == 16


def test_answers_on_a_bound_and_clipped_draws_are_announced() -> None:
    from invphys.inverter.draws import sample_posterior
    from invphys.inverter.uncertainty import Uncertainty, answer_warnings

    w = answer_warnings(Uncertainty(), ("a", "b"), np.array([0.0, 0.5]), np.ones(3, bool))
    assert w == ["the answer sits on a bound of the parameter box (the truth may lie beyond it): a at its lower bound"]

    class Outside:  # a posterior with all its mass outside the box: rejection hits its cap
        def sample(self, shape, condition):
            import torch

            return torch.full((*shape, condition.shape[0], 2), 2.0)

    class Plugin:
        class _posterior:
            posterior_estimator = Outside()

    d = sample_posterior(Plugin(), [np.zeros((1, 3))], [1], 10)
    assert d.clipped[0] == 10 and d.outside_fraction[0] == 1.0 and np.all(d.samples == 1.0)
    w = answer_warnings(Uncertainty("posterior", d.samples[0], clipped=10, outside_fraction=1.0), ("a", "b"),
                        np.array([0.5, 0.5]), np.ones(3, bool))
    assert any("10 posterior draws were clipped" in x for x in w)


def test_cli_writes_draws_plot_and_table_and_refuses_bad_input_before_work(inv, y, tmp_path) -> None:
    from typer.testing import CliRunner

    from invphys.cli import app

    f = tmp_path / "t.json"
    f.write_text(json.dumps(dict(zip(inv.feature_names, map(float, y[1]), strict=True))))
    root = str(inv.bundle.root)
    res = CliRunner().invoke(app, ["invert", root, "--target", str(f), "--samples", "300", "--samples-out",
                                   str(tmp_path / "d.npz"), "--plot", str(tmp_path / "p.png"), "--csv",
                                   str(tmp_path / "t.csv"), "--level", "0.8", "--json"])
    assert res.exit_code == 0, res.output
    with np.load(tmp_path / "d.npz", allow_pickle=False) as z:
        assert z["samples"].shape == (1, 300, 9) and list(z["parameter_names"]) == list(inv.parameter_names)
    assert (tmp_path / "p.png").stat().st_size > 1000 and "E_low" in (tmp_path / "t.csv").read_text()
    assert json.loads(res.stdout)["results"][0]["posterior"]["level"] == 0.8
    (tmp_path / "file").write_text("x")
    for extra, msg in ((["--seed", "-1"], "seed"), (["--top-k", "1000000"], "at most 64"),
                       (["--samples", "5", "--samples-out", str(tmp_path / "t.csv")], "exists"),
                       (["--polish", "4", "--polish-log", str(tmp_path / "file" / "log.npz")], "is a file"),
                       (["--level", "1.5"], "level")):
        r = CliRunner().invoke(app, ["invert", root, "--target", str(f), *extra])
        assert r.exit_code == 2 and msg in r.output and "Traceback" not in r.output, (extra, r.output)
