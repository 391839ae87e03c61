"""Saved NPE flows rebuilt without sbi (invphys.plugins.baselines.npe_flows) are sbi's flows, bit for bit.

Loading a bundle's maf and nsf flows no longer goes through sbi's builder (whose import pulls scikit-learn and
scipy.stats, a second of a one-target answer). These tests fail when the rebuilt network differs from sbi's
(keys, shapes, weights), when a draw or log-prob differs in any bit from sbi's ``DirectPosterior``
(``sample_batched`` / ``log_prob_batched`` without rejection, as the baseline drew before), when answering
from a saved bundle imports sbi again, or when a layout the builder does not make is not left to sbi.
"""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("sbi")
torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[1]
BUNDLE = ROOT / "inverters" / "orange_peel_paper_all"
#: a plain nsf, a logit nsf and a maf (the shipped bundle's other flows share these architectures)
FLOWS = ("npe_nsf", "npe_nsfLogit", "npe_best64")


def sbi_posterior(label: str):
    """The shipped flow ``label``'s save rebuilt through sbi's builder: sbi's ``DirectPosterior`` (a bundle loads
    it without sbi)."""
    import json

    from invphys.models.base import read_weights_npz
    from invphys.plugins.baselines.npe import NPEBaseline

    d = BUNDLE / "policies" / label
    arch = json.loads((d / "npe.json").read_text())["architecture"]
    return NPEBaseline.load(d)._rebuild_with_sbi(arch["theta_dim"], arch["x_dim"], read_weights_npz(d / "npe_weights.npz"), d)


def _both(label: str):
    """The flow loaded (the light builder) and the same save rebuilt through sbi's builder."""
    from invphys.plugins.baselines.npe import NPEBaseline

    light, heavy = NPEBaseline.load(BUNDLE / "policies" / label), NPEBaseline.load(BUNDLE / "policies" / label)
    heavy._posterior = sbi_posterior(label)
    return light, heavy


@pytest.fixture(scope="module")
def targets() -> np.ndarray:
    """Held-out rows and fresh edge targets (much of their mass outside the box: -inf log-probs)."""
    from invphys.core.dataset import DatasetStore

    edge = DatasetStore(ROOT / "datasets" / "orange_peel_paper_fresh_edge").arrays(ok_only=True).y
    held = np.load(BUNDLE / "data" / "test.npz")["y"]
    return np.concatenate([held[:4], edge[:4]]).astype(np.float64)


def _sbi_draw(plugin, target: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """What NPEBaseline drew before the light builder: sbi's DirectPosterior, no rejection, no leakage factor."""
    x = torch.as_tensor(target[None, :], dtype=torch.float32)
    with torch.random.fork_rng(devices=[]), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.manual_seed(seed)
        s = plugin._posterior.sample_batched((n,), x=x, show_progress_bars=False, reject_outside_prior=False)
        lp = plugin._posterior.log_prob_batched(s, x=x, norm_posterior=False)
    samples, logp = s.numpy().astype(np.float64)[:, 0, :], lp.numpy().astype(np.float64)[:, 0]
    if plugin.config.transform == "logit":
        samples = 1.0 / (1.0 + np.exp(-samples))
        logp = logp - np.log(np.clip(samples * (1.0 - samples), 1e-300, None)).sum(axis=1)
    return samples, logp


@pytest.mark.parametrize("label", FLOWS)
def test_the_rebuilt_flow_is_sbis_flow(label) -> None:
    from invphys.plugins.baselines.npe_flows import FlowEstimator, LoadedPosterior

    light, heavy = _both(label)
    assert type(light._posterior) is LoadedPosterior and type(light._posterior.posterior_estimator) is FlowEstimator
    assert type(heavy._posterior).__name__ == "DirectPosterior"
    a, b = light._posterior.posterior_estimator, heavy._posterior.posterior_estimator
    assert [type(m).__name__ for m in a.net.modules()][1:] == [type(m).__name__ for m in b.net.modules()][1:]
    sa, sb = a.state_dict(), b.state_dict()
    assert list(sa) == list(sb)
    assert all(torch.equal(sa[k], sb[k]) and sa[k].dtype == sb[k].dtype for k in sa)
    assert (a.input_shape, a.condition_shape) == (b.input_shape, b.condition_shape)
    assert a.net._distribution._log_z.dtype == b.net._distribution._log_z.dtype == torch.float32


@pytest.mark.parametrize("label", FLOWS)
def test_draws_and_log_probs_are_sbis(label, targets) -> None:
    light, heavy = _both(label)
    outside = 0
    for i, t in enumerate(targets):
        want = _sbi_draw(heavy, t, 96, 500 + i)
        got = light._draw_one(t, 96, 500 + i)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        outside += int(np.isinf(got[1]).sum())
    if light.config.transform != "logit":
        assert outside > 0, "no draw fell outside the box: the -inf mask went untested"
    s, lp = light.posterior_samples(targets[:3], 32)
    s2, lp2 = heavy.posterior_samples(targets[:3], 32)
    np.testing.assert_array_equal(s, s2)
    np.testing.assert_array_equal(lp, lp2)


def test_a_layout_the_builder_does_not_make_is_left_to_sbi() -> None:
    from invphys.models.base import read_weights_npz
    from invphys.plugins.baselines.npe_flows import load_estimator

    state = read_weights_npz(BUNDLE / "policies" / "npe_nsf" / "npe_weights.npz")
    assert load_estimator("nsf", 64, 5, 9, 12, state) is not None
    assert load_estimator("mdn", 64, 5, 9, 12, state) is None  # no light mdn
    assert load_estimator("nsf", 64, 4, 9, 12, state) is None  # keys of another layout
    assert load_estimator("nsf", 32, 5, 9, 12, state) is None  # shapes of another layout
    renamed = {("net._embedding_net.0.mean" if k == "net._embedding_net.0._mean" else k): v for k, v in state.items()}
    assert load_estimator("nsf", 64, 5, 9, 12, renamed) is None
    rng = torch.get_rng_state()
    load_estimator("maf", 50, 5, 9, 12, read_weights_npz(BUNDLE / "policies" / "npe_best64" / "npe_weights.npz"))
    assert torch.equal(torch.get_rng_state(), rng), "building the flow moved the caller's torch stream"


def test_answering_from_a_saved_bundle_imports_no_sbi() -> None:
    """A fresh process that loads the shipped all-data bundle and answers a target with its default (the
    pool of four nsf flows) and with a maf (npe_best64) imports neither sbi nor scikit-learn nor scipy.stats."""
    probe = (
        "import sys, numpy as np\n"
        "from invphys.inverter import load_inverter\n"
        f"inv = load_inverter({str(BUNDLE)!r})\n"
        f"y = np.load({str(BUNDLE / 'data' / 'test.npz')!r})['y'][0]\n"
        "a = inv.invert(dict(zip(inv.feature_names, y.tolist())))\n"
        "b = inv.invert(dict(zip(inv.feature_names, y.tolist())), method='npe_best64')\n"
        "print(a.method, b.method, [m for m in ('sbi', 'sklearn', 'scipy.stats') if m in sys.modules])\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.split()[-1] == "[]", out.stdout + out.stderr
