"""The active stage's saved rounds (``progress.npz``) are keyed by how answers are seeded: rounds saved under
another seeding (refinements seeded by position, before per-target seeding) start over, never resume."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np


def _ctx(tmp_path):
    """What ``_checkpoint_key`` and the checkpoint files read of a stage context: a toy run's spec parts."""
    from invphys.registry import default_registry

    reg = default_registry()
    sim_block = {"type": "test_dataset_toy:ToyOscillator"}
    sim = reg.create("simulator", sim_block)
    extractor = reg.create("feature_extractor", {"type": sim.default_feature_extractor()})
    spec = SimpleNamespace(active=None, surrogate={"type": "mlp"}, validator={"type": "simulator", "batch_size": 8},
                           simulator=sim_block)
    logged: list[str] = []
    ctx = SimpleNamespace(spec=spec, seed=3, simulator=lambda: sim, extractor=lambda: extractor,
                          dataset=lambda: SimpleNamespace(fingerprint="f" * 16), stage_dir=tmp_path, log=logged.append)
    return ctx, logged


def _save(ctx, key):
    from invphys.pipeline.stages.active import _save_checkpoint

    theta, y = np.full((2, 3), 0.5), np.ones((2, 4))
    _save_checkpoint(ctx, key, [{"round": 0}], (theta, np.zeros(2), y), [theta], [y])


def test_rounds_saved_under_another_seeding_are_not_resumed(tmp_path, monkeypatch) -> None:
    from invphys.pipeline import cache
    from invphys.pipeline.stages.active import _checkpoint_key, _load_checkpoint

    ctx, logged = _ctx(tmp_path)
    feats = np.arange(8.0).reshape(2, 4)

    def keys():
        return _checkpoint_key(ctx, 2, feats), _checkpoint_key(ctx, 2, feats, legacy=True)

    now = keys()
    _save(ctx, now[0])
    assert _load_checkpoint(ctx, now)["rounds"] == [{"round": 0}]  # the same settings resume
    for old in (0, 1):  # rounds saved under the position seeding, by either form of the key
        with monkeypatch.context() as m:
            m.setattr(cache, "SEEDING", "by-position")
            before = keys()
        assert set(before).isdisjoint(now)
        _save(ctx, before[old])
        logged.clear()
        assert _load_checkpoint(ctx, now) is None
        assert logged == ["progress.npz was made with other settings; starting from round 0"]
