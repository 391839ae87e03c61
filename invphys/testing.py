"""Conformance checks for plugin authors (in the spirit of Gymnasium's ``check_env``).

Call them from your own tests::

    from invphys.testing import check_plugin_class, check_simulator

    def test_my_simulator_conforms():
        check_plugin_class(MySimulator)
        check_simulator(MySimulator(preset="tiny"), n_runs=2)

Each check raises :class:`ConformanceError` with a message naming what is wrong.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import ValidationError

from invphys.core.interfaces import (
    PLUGIN_KINDS,
    FeatureExtractor,
    LatentModel,
    Plugin,
    PluginConfig,
    Simulator,
    Surrogate,
)
from invphys.core.results import SimulationResult


class ConformanceError(AssertionError):
    """A plugin does not meet its interface's contract."""


def _fail(cls: Any, message: str) -> ConformanceError:
    name = getattr(cls, "__qualname__", type(cls).__qualname__)
    return ConformanceError(f"{name}: {message}")


def check_plugin_class(cls: type[Plugin]) -> None:
    """Static contract of any plugin class: kind, name, a forbidding Config with defaults, docstrings."""
    kind = getattr(cls, "kind", None)
    if kind not in PLUGIN_KINDS or not issubclass(cls, PLUGIN_KINDS[kind]):
        raise _fail(cls, f"does not subclass one of the interfaces {sorted(PLUGIN_KINDS)}")
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name or not name.replace("_", "").isalnum() or name != name.lower():
        raise _fail(cls, f"name must be a lower-case identifier, got {name!r}")
    if not (isinstance(cls.Config, type) and issubclass(cls.Config, PluginConfig)):
        raise _fail(cls, "Config must subclass invphys.core.interfaces.PluginConfig")
    if cls.Config.model_config.get("extra") != "forbid":
        raise _fail(cls, "Config must forbid unknown fields (extra='forbid')")
    try:
        cls.Config()
    except ValidationError as exc:
        raise _fail(cls, f"Config() must construct from defaults alone: {exc}") from exc
    try:
        cls.Config(**{"__not_a_field__": 1})
    except ValidationError:
        pass
    else:
        raise _fail(cls, "Config accepted an unknown field")
    if not (cls.__doc__ or "").strip():
        raise _fail(cls, "needs a docstring (it becomes the API reference and the schema description)")


def check_simulator(sim: Simulator, n_runs: int = 2, seed: int = 0) -> list[SimulationResult]:
    """Run ``n_runs`` random parameter vectors and check the results' shapes, order and provenance."""
    space = sim.parameter_space()
    rng = np.random.default_rng(seed)
    params = space.denormalize(rng.uniform(0, 1, size=(n_runs, space.dim)))
    seen: list[int] = []
    results = sim.simulate(params, on_result=lambda i, r: seen.append(i))
    if len(results) != n_runs:
        raise _fail(sim, f"simulate returned {len(results)} results for {n_runs} parameter vectors")
    if sorted(seen) != list(range(n_runs)):
        raise _fail(sim, f"on_result must be called once per row, got rows {seen}")
    for i, res in enumerate(results):
        if not np.allclose(res.params, params[i]):
            raise _fail(sim, f"result {i} carries params {res.params}, expected {params[i]}")
        if res.ok:
            t = res.trajectory
            if t is None and res.features is None:
                raise _fail(sim, f"ok result {i} has neither a trajectory nor features")
            if t is not None:
                if t.positions.ndim != 3 or t.positions.shape[2] != 3:
                    raise _fail(sim, f"positions must be (T, N, 3), got {t.positions.shape}")
                if t.damage.shape != t.positions.shape[:2] or t.labels.shape != t.positions.shape[1:2]:
                    raise _fail(sim, "damage must be (T, N) and labels (N,)")
                if not np.isfinite(t.positions).all():
                    raise _fail(sim, "an ok run has non-finite positions (report it as failed instead)")
        elif not res.failure:
            raise _fail(sim, f"failed result {i} must give a failure reason")
        if not res.stats.simulator_version and not res.stats.backend:
            raise _fail(sim, "RunStats must record at least the backend and simulator version")
    return results


def check_feature_extractor(extractor: FeatureExtractor, results: list[SimulationResult]) -> np.ndarray:
    """Extract features of the ok results and check shape, names and finiteness."""
    names = extractor.feature_names
    if len(set(names)) != len(names):
        raise _fail(extractor, "feature names must be unique")
    rows = [extractor.extract(r.trajectory) for r in results if r.ok and r.trajectory is not None]
    if not rows:
        raise _fail(extractor, "no ok trajectory to extract from")
    y = np.stack(rows)
    if y.shape[1] != len(names):
        raise _fail(extractor, f"extract returned {y.shape[1]} values for {len(names)} names")
    if not np.isfinite(y).all():
        raise _fail(extractor, "features must be finite (handle degenerate runs deliberately)")
    return y


def check_surrogate(model: Surrogate, theta: np.ndarray, y: np.ndarray, tmp_dir: Any) -> None:
    """A fitted surrogate predicts (B, M), and save/load reproduces its predictions exactly."""
    pred = model.predict(theta)
    if pred.shape != y.shape:
        raise _fail(model, f"predict returned {pred.shape}, expected {y.shape}")
    mean, std = model.predict_with_uncertainty(theta)
    if mean.shape != y.shape or std.shape != y.shape or (std < 0).any():
        raise _fail(model, "predict_with_uncertainty must return (mean, std >= 0) of shape (B, M)")
    loaded = type(model).load(model.save(tmp_dir))
    if not np.array_equal(loaded.predict(theta), pred):  # type: ignore[attr-defined]
        raise _fail(model, "save/load changed the predictions")


def check_latent_model(model: LatentModel, theta: np.ndarray) -> float:
    """encode/decode shapes, decode within [0, 1]; returns the reconstruction MSE."""
    z = model.encode(theta)
    if z.shape != (len(theta), model.latent_dim):
        raise _fail(model, f"encode returned {z.shape}, expected {(len(theta), model.latent_dim)}")
    back = model.decode(z)
    if back.shape != theta.shape or back.min() < 0 or back.max() > 1:
        raise _fail(model, "decode must return (B, d) within [0, 1]")
    return float(np.mean((back - theta) ** 2))
