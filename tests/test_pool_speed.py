"""The pool's fast paths give the answers of the plain ones (shipped paper bundle, a private copy).

``tests/data/pool_answers_golden.npz`` holds answers the pool gave BEFORE its speed work (draws of the
extra members in whole rounds, every target scored alone): a two-member ensemble pool (the NPE and a
second label of the same flow, its own per-target stream), plain and with ``exact``, top 3 candidates,
complete and partial targets. Rewrite it (only after a deliberate change of answers) with
``python tests/test_pool_speed.py --write``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).parent / "data" / "pool_answers_golden.npz"
VARIANTS = {"plain": {}, "exact": {"exact": True, "margin": 0.02}}
DROP = ("fracture_onset_frame", "peeling_work")


def _targets(inv) -> list[dict[str, float]]:
    _, y = inv.bundle.data("test")
    full = [dict(zip(inv.feature_names, map(float, r), strict=True)) for r in y[:30]]
    return full + [{k: v for k, v in t.items() if k not in DROP} for t in full[:4]]


def _answers(inv, variant: str, order: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per target (in the targets' own order): candidates' theta and R_surr, the draws' mean and 5/50/95 %
    quantiles, the outside fraction; ``order``: answer the targets in that order (then put back)."""
    from invphys.inverter.pool import PoolSettings

    targets = _targets(inv)
    idx = np.arange(len(targets)) if order is None else np.asarray(order)
    inv.bundle.methods["npe_b"] = dict(inv.bundle.methods["npe_best64"])
    inv.pool_settings = PoolSettings(extra=("npe_b",)).with_(**VARIANTS[variant])
    try:
        got = inv.invert_many([targets[i] for i in idx], method="pool", seed=5, top_k=3, partial=True)
    finally:
        from invphys.inverter.pool import PoolSettings as P

        inv.pool_settings = P()
        inv.bundle.methods.pop("npe_b")
        inv._plugins.pop("npe_b", None)
    res = [None] * len(targets)
    for i, r in zip(idx, got, strict=True):
        res[i] = r
    draws = np.stack([r.parameter_uncertainty.draws for r in res])
    return {"theta": np.stack([np.stack([c.theta for c in r.candidates]) for r in res]),
            "r_surrogate": np.array([[c.r_surrogate for c in r.candidates] for r in res]),
            "draws_mean": draws.mean(axis=1),
            "draws_q": np.quantile(draws, [0.05, 0.5, 0.95], axis=1).transpose(1, 0, 2),
            "outside": np.array([r.parameter_uncertainty.outside_fraction for r in res])}


@pytest.fixture(scope="module")
def inv(tmp_path_factory):
    from test_inverter_support import paper_inverter

    return paper_inverter(tmp_path_factory.getbasetemp())


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_the_pool_answers_as_it_did_before_its_speed_work(inv, variant) -> None:
    """Candidates, R_surr, interval draws and outside fraction as the golden file holds them (written by
    the pool before its speed work; equal to the last bits on the machine that wrote them)."""
    golden = np.load(GOLDEN)
    got = _answers(inv, variant)
    for key, value in got.items():
        np.testing.assert_allclose(value, golden[f"{variant}.{key}"], rtol=0, atol=1e-6, err_msg=key)


def test_the_answers_do_not_depend_on_the_targets_order(inv) -> None:
    golden = np.load(GOLDEN)
    order = np.random.default_rng(3).permutation(len(_targets(inv)))
    got = _answers(inv, "plain", order)
    for key, value in got.items():
        np.testing.assert_allclose(value, golden[f"plain.{key}"], rtol=0, atol=1e-6, err_msg=key)


def test_rounds_in_part_give_the_draws_of_whole_rounds(inv) -> None:
    """Draws whose outside fraction nobody reads (a pool's extra members) stop a round where the n-th
    draw inside is found: the same draws bit for bit (and sbi's own, target by target), fewer rows."""
    from invphys.inverter import draws as D

    plugin = inv._plugin("npe_best64", inv._entry("npe_best64")[1])[0]
    _, y = inv.bundle.data("test")
    mean = np.asarray(inv.bundle.manifest["features"]["mean"])
    full = np.ones(y.shape[1], bool)
    part = full.copy()
    part[[2, 5]] = False
    train_y = inv.bundle.data("train")[1]
    conds = [D.completions(v, full, None, mean, inv.bundle.scales) for v in y[:40]]
    conds += [D.completions(v, part, train_y, mean, inv.bundle.scales) for v in y[40:43]]
    seeds = list(range(100, 100 + len(conds)))
    whole = D.sample_posterior(plugin, conds, seeds, 64)
    fast = D.sample_posterior(plugin, conds, seeds, 64, whole_rounds=False)
    np.testing.assert_array_equal(fast.samples, whole.samples)
    assert fast.raw_draws.sum() < 0.7 * whole.raw_draws.sum()
    est = plugin._posterior.posterior_estimator
    for i in (0, 17, 39, 41):
        np.testing.assert_array_equal(fast.samples[i], D._one(est, conds[i], seeds[i], 64, False)[0])
    for i in (3, 29):  # alone: the same draws
        alone = D.sample_posterior(plugin, conds[i:i + 1], seeds[i:i + 1], 64, whole_rounds=False)
        np.testing.assert_array_equal(alone.samples[0], whole.samples[i])


def test_no_real_row_ends_a_flow_call() -> None:
    """The flow computes a call's last rows otherwise than the others (rarely, in the last bits): every
    call ends in at least PAD rows of padding, and holds at least a round."""
    import torch

    from invphys.inverter import draws as D

    for n in (1, 100, D.ROUND - 1, D.ROUND, 3 * D.ROUND):
        x = torch.arange(float(n * 2)).reshape(n, 2)
        p = D._padded(x)
        assert len(p) >= max(n + D.PAD, D.ROUND) and len(p) % D.PAD == 0 and torch.equal(p[:n], x)


def write(base: Path) -> None:
    from test_inverter_support import paper_inverter

    inv = paper_inverter(base)
    out = {f"{v}.{k}": a for v in VARIANTS for k, a in _answers(inv, v).items()}
    GOLDEN.parent.mkdir(exist_ok=True)
    np.savez_compressed(GOLDEN, **out)
    print(f"wrote {GOLDEN}: {sorted(out)}")


if __name__ == "__main__" and "--write" in sys.argv:
    import tempfile

    sys.path.insert(0, str(Path(__file__).parent))
    with tempfile.TemporaryDirectory() as tmp:
        write(Path(tmp))
