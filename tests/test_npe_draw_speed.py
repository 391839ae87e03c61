"""The spline sampler draws what nflows and sbi draw, to the last bit (shipped orange_peel_paper_all flows).

The inverter's posterior draws of sbi's ``nsf`` flows (``pool_nsf4``'s four members) go through
:class:`~invphys.plugins.baselines.spline_sampler.SplineSampler` instead of nflows' own inverse
(:mod:`invphys.inverter.draws`). These tests fail when one of its draws differs in any bit from nflows'
inverse, from sbi's ``sample_batched`` under the target's seed, or between a target drawn alone, in a batch
and in a reversed batch.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("sbi")
torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[1]
BUNDLE = ROOT / "inverters" / "orange_peel_paper_all"
FLOWS = ("npe_nsf", "npe_nsfLogit")  # a plain and a logit nsf (the other two members: same architecture)


@pytest.fixture(scope="module")
def flows():
    from invphys.plugins.baselines.npe import NPEBaseline

    return {label: NPEBaseline.load(BUNDLE / "policies" / label) for label in FLOWS}


@pytest.fixture(scope="module")
def targets() -> np.ndarray:
    """Held-out rows and fresh edge targets (most of their mass outside the box: many rounds)."""
    from invphys.core.dataset import DatasetStore

    edge = DatasetStore(ROOT / "datasets" / "orange_peel_paper_fresh_edge").arrays(ok_only=True).y
    held = np.load(BUNDLE / "data" / "test.npz")["y"]
    return np.concatenate([held[:8], edge[:8]]).astype(np.float64)


def _net(plugin):
    from invphys.inverter import draws as D

    return D._flow(plugin._posterior.posterior_estimator)


def _seeds(n: int) -> list[int]:
    return [1000 + 7 * i for i in range(n)]


def test_the_sampler_computes_sbis_nsf_only(flows) -> None:
    from invphys.plugins.baselines.npe import NPEBaseline
    from invphys.plugins.baselines.spline_sampler import spline_sampler

    for plugin in flows.values():
        assert spline_sampler(_net(plugin)) is not None
    maf = NPEBaseline.load(BUNDLE / "policies" / "npe_best64")  # another flow: nflows' own inverse draws it
    assert spline_sampler(_net(maf)) is None


@pytest.mark.parametrize("label", FLOWS)
def test_its_rows_are_nflows_rows(flows, targets, label) -> None:
    """Padded calls of several sizes, base noise up to 3 sigma wider (entries past the splines' tail bound)
    and the gates of 1,500 conditions at once: every real row equals nflows' inverse."""
    from invphys.inverter import draws as D
    from invphys.plugins.baselines.spline_sampler import spline_sampler

    net = _net(flows[label])
    sampler = spline_sampler(net)
    held = np.load(BUNDLE / "data" / "test.npz")["y"]
    gen = torch.Generator().manual_seed(4)
    with D._torch_stream(0), torch.no_grad():  # one torch thread, as the draws are made
        emb = net._embedding_net(torch.as_tensor(np.concatenate([held, targets]), dtype=torch.float32))
        gates = sampler.gates(D._padded(emb))
        for rows, wide in ((250, 1.0), (1000, 2.0), (4096, 3.0)):
            r = torch.randint(0, len(emb), (rows,), generator=gen)
            z = torch.randn(rows, int(net._distribution._shape[0]), generator=gen) * wide
            zp, rp = D._padded(z), D._padded(r[:, None])[:, 0]
            want = net._transform.inverse(zp, context=emb[rp])[0][:rows]
            got = sampler.inverse(zp, emb[rp], [g[rp] for g in gates])[:rows]
            assert torch.equal(got, want), f"{rows} rows: {int((got != want).any(1).sum())} differ"


@pytest.fixture()
def counted(monkeypatch):
    """Calls of the sampler's inverse (so that an equality below is not nflows against itself)."""
    from invphys.plugins.baselines import spline_sampler as ss

    calls = []
    inverse = ss.SplineSampler.inverse

    def wrapped(self, *a, **kw):
        calls.append(1)
        return inverse(self, *a, **kw)

    monkeypatch.setattr(ss.SplineSampler, "inverse", wrapped)
    return calls


@pytest.mark.parametrize("label", FLOWS)
def test_draws_are_nflows_draws(flows, targets, label, counted, monkeypatch) -> None:
    """Through the inverter's sampling (whole rounds and rounds in part, complete and partial targets):
    draws, outside fractions, clipped and raw counts equal those of nflows' own inverse."""
    from invphys.inverter import draws as D
    from invphys.plugins.baselines import spline_sampler as ss

    plugin = flows[label]
    held = np.load(BUNDLE / "data" / "test.npz")["y"]
    full = np.ones(targets.shape[1], bool)
    part = full.copy()
    part[[2, 5]] = False
    mean = held.mean(axis=0)
    scales = held.std(axis=0)
    conds = [D.completions(v, full, None, mean, scales) for v in targets]
    conds += [D.completions(v, part, held[100:], mean, scales) for v in targets[:2]]
    seeds = _seeds(len(conds))
    for n, whole in ((256, True), (64, False)):
        fast = D.sample_posterior(plugin, conds, seeds, n, whole_rounds=whole)
        assert counted, "the spline sampler did not draw"
        with monkeypatch.context() as m:
            m.setattr(ss, "spline_sampler", lambda net: None)
            plain = D.sample_posterior(plugin, conds, seeds, n, whole_rounds=whole)
        for key in ("samples", "outside_fraction", "clipped", "raw_draws", "completions"):
            np.testing.assert_array_equal(getattr(fast, key), getattr(plain, key), err_msg=f"{key}, {n} draws")


@pytest.mark.parametrize("label", FLOWS)
def test_a_target_draws_the_same_alone_in_a_batch_and_reversed(flows, targets, label) -> None:
    from invphys.inverter import draws as D

    plugin = flows[label]
    conds, seeds = [v[None, :] for v in targets], _seeds(len(targets))
    batch = D.sample_posterior(plugin, conds, seeds, 256)
    back = D.sample_posterior(plugin, conds[::-1], seeds[::-1], 256)
    np.testing.assert_array_equal(back.samples[::-1], batch.samples)
    np.testing.assert_array_equal(back.outside_fraction[::-1], batch.outside_fraction)
    for i in (0, 5, 9, 15):
        alone = D.sample_posterior(plugin, conds[i:i + 1], seeds[i:i + 1], 256)
        np.testing.assert_array_equal(alone.samples[0], batch.samples[i])
        assert alone.raw_draws[0] == batch.raw_draws[i]


@pytest.mark.parametrize("label", FLOWS)
def test_the_first_round_is_sbis_own_sample(flows, targets, label) -> None:
    """sbi's ``sample_batched`` (no rejection) under the target's seed: its rows are the sampler's first
    round, and those inside the box are the target's first draws, in order. sbi's own call is not padded, so
    its last :data:`~invphys.inverter.draws.PAD` rows may differ in the last bit (a vector loop's scalar tail)
    and are left out."""
    from invphys.inverter import draws as D
    from invphys.plugins.baselines.spline_sampler import spline_sampler

    plugin = flows[label]
    from test_npe_flows import sbi_posterior

    post, net = sbi_posterior(label), _net(plugin)
    sampler = spline_sampler(net)
    logit = plugin.config.transform == "logit"
    for i in (0, 3, 8, 12):
        seed = 500 + i
        x = torch.as_tensor(targets[i][None, :], dtype=torch.float32)
        with D._torch_stream(seed), torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sbi = post.sample_batched((D.ROUND,), x=x, reject_outside_prior=False, show_progress_bars=False)[:, 0]
            noise = torch.randn(D.ROUND, sbi.shape[1], generator=torch.Generator().manual_seed(seed))
            emb = net._embedding_net(x)
            rows = torch.zeros(len(D._padded(noise)), dtype=torch.long)
            ours = sampler.inverse(D._padded(noise), emb[rows], [g[rows] for g in sampler.gates(D._padded(emb))])
        k = D.ROUND - D.PAD
        assert torch.equal(ours[:k], sbi[:k])
        raw = sbi[:k].numpy().astype(np.float64)
        raw = 1.0 / (1.0 + np.exp(-raw)) if logit else raw
        inside = raw[np.all((raw >= 0) & (raw <= 1), axis=1)]
        drawn = D.sample_posterior(plugin, [targets[i][None, :]], [seed], D.ROUND).samples[0]
        np.testing.assert_array_equal(drawn[:len(inside)], inside)
