"""corrected_search answers each target from a stream of its own (seeded from ``seed`` and the target's values):
the answers do not depend on the targets' order or on the batch; the plugin's version records the change, so
stage keys and the baselines' answer cache do not serve answers made with one stream for the whole batch."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from invphys.core.objectives import percentile_scales
from invphys.plugins.baselines import CorrectedSearch


def _forward(theta: np.ndarray) -> np.ndarray:
    t = np.atleast_2d(theta)
    return np.c_[t[:, 0] + 0.3 * t[:, 1] ** 2, t[:, 1] - 0.2 * t[:, 2], np.sin(2 * t[:, 2]), t[:, 0] * t[:, 1]]


def _biased(theta: np.ndarray) -> np.ndarray:
    """A surrogate that computes each row alone (so any batch effect would be the plugin's)."""
    th = np.atleast_2d(theta)
    return _forward(th) + 0.05 * np.c_[th[:, :1], -th[:, 1:2], 0.5 + 0 * th[:, :1], th[:, 2:3]]


def test_answers_do_not_depend_on_the_order_or_the_batch() -> None:
    rng = np.random.default_rng(0)
    theta = rng.uniform(0, 1, (300, 3))
    y = _forward(theta)
    targets = _forward(rng.uniform(0.1, 0.9, (12, 3)))
    cs = CorrectedSearch(k=20, ridge=1e-3, neighbours=8, budget=48, bandwidth=0.2, seed=3)
    cs.fit(theta, y, percentile_scales(y))
    fwd = cs.answer(targets, _biased)
    rev = cs.answer(targets[::-1], _biased)
    np.testing.assert_array_equal(rev.theta[::-1], fwd.theta)
    np.testing.assert_array_equal(rev.candidates[::-1], fwd.candidates)
    for i in (0, 5, 11):  # one target alone gets the answer it gets among the others
        alone = cs.answer(targets[i:i + 1], _biased)
        np.testing.assert_array_equal(alone.theta[0], fwd.theta[i])
        np.testing.assert_array_equal(alone.candidates[0], fwd.candidates[i])
    # the seed still matters: another seed perturbs other candidates
    other = CorrectedSearch(k=20, ridge=1e-3, neighbours=8, budget=48, bandwidth=0.2, seed=4)
    other.fit(theta, y, percentile_scales(y))
    assert not np.array_equal(other.answer(targets, _biased).candidates, fwd.candidates)


def test_the_change_reaches_stage_keys_and_the_baselines_cache_key() -> None:
    """The stage keys record ``corrected_search``'s own version (a run cached with the batch-wide stream
    re-runs); the baselines' answer cache is keyed by it too, while a baseline without a version keeps
    the key it had."""
    from invphys.pipeline import cache
    from invphys.pipeline.stage_files import _own_versions
    from invphys.registry import default_registry

    reg = default_registry()
    blocks = {"cs": {"type": "corrected_search", "budget": 48}, "nn": {"type": "nearest_neighbour"}}
    spec = SimpleNamespace(plugin_blocks=lambda: [(f"optimizers.{k}", "optimizer", b) for k, b in blocks.items()])
    versions = cache.plugin_versions(spec, ("optimizers",), reg)
    assert versions["optimizers.cs"].endswith("/2") and "/" not in versions["optimizers.nn"].partition("==")[2]
    assert _own_versions(SimpleNamespace(registry=reg), blocks) == {"cs": "2"}
    assert _own_versions(SimpleNamespace(registry=reg), {"nn": blocks["nn"]}) == {}


def _baselines_ctx(tmp_path, blocks):
    """What :func:`~invphys.pipeline.stage_files.baselines` reads of a stage context (a stand-in surrogate)."""
    from invphys.registry import default_registry

    rng = np.random.default_rng(1)
    theta = rng.uniform(0, 1, (120, 3))
    y = _forward(theta)

    def no_simulator():
        raise RuntimeError("not built here")

    spec = SimpleNamespace(evaluation=SimpleNamespace(baselines=blocks), section_dump=lambda names: {"dataset": {}})
    return SimpleNamespace(spec=spec, seed=2, registry=default_registry(), stage_dir=tmp_path,
                           stage_dir_of=lambda stage: tmp_path / stage, log=lambda msg: None,
                           dataset=lambda: SimpleNamespace(theta=theta, y=y),
                           split=lambda: (np.arange(100), np.arange(100, 120)), scales=lambda: percentile_scales(y),
                           surrogate=lambda: SimpleNamespace(predict=_biased), simulator=no_simulator)


def test_a_cache_of_the_batch_wide_stream_is_not_served(tmp_path) -> None:
    """``baselines.json`` written under the key the cache had before (no versions) is answered afresh for
    corrected_search, and still served for a baseline that declares no version."""
    import json

    from invphys.pipeline.cache import SEEDING
    from invphys.pipeline.runner import fingerprint
    from invphys.pipeline.stage_files import BASELINES_FILE, baselines

    targets = {"rows": [100, 101], "features": _forward(np.array([[0.3, 0.4, 0.5], [0.6, 0.2, 0.7]])).tolist(),
               "param_names": ["a", "b", "c"]}
    for blocks, served in (({"cs": {"type": "corrected_search", "budget": 48}}, False),
                           ({"nn": {"type": "nearest_neighbour"}}, True)):
        ctx = _baselines_ctx(tmp_path, blocks)
        old_key = fingerprint({"baselines": blocks, "rows": targets["rows"], "features": targets["features"],
                               "dataset": {"dataset": {}}, "seed": 2, "train": None, "seeding": SEEDING})
        stale = [{"optimizer": next(iter(blocks)), "stale": True}]
        (tmp_path / BASELINES_FILE).write_text(json.dumps({"key": old_key, "rows": stale, "metrics": {}}))
        rows, _ = baselines(ctx, targets)
        assert (rows == stale) is served
        if not served:
            assert len(rows) == 2 and all("theta" in r for r in rows)
            again = baselines(ctx, targets)[0]  # the fresh answers are cached under the new key
            assert [r["theta"] for r in again] == [r["theta"] for r in rows]
            assert json.loads((tmp_path / BASELINES_FILE).read_text())["key"] != old_key
