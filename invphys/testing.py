"""Conformance checks for plugin authors (in the spirit of Gymnasium's ``check_env``).

Call them from your own tests::

    from invphys.testing import check_plugin_class, check_render, check_simulator

    def test_my_simulator_conforms(tmp_path):
        check_plugin_class(MySimulator)
        results = check_simulator(MySimulator(preset="tiny"), n_runs=2)
        check_deterministic(MySimulator(preset="tiny"))
        check_trajectory_file(results[0].trajectory, tmp_path)
        check_render(MySimulator(preset="tiny"), results[0].trajectory, tmp_path / "render")

Each check raises :class:`ConformanceError` with a message naming what is wrong.
``docs/writing-a-simulator.md`` lists what each one checks.
"""

from __future__ import annotations

from pathlib import Path
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
from invphys.core.results import Rendering, SimulationResult, Trajectory


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
    """Run ``n_runs`` random parameter vectors and check the results' shapes, order and provenance.

    Checks: one result per row, in order, each carrying its own ``params``; ``on_result`` called once
    per row; an ok result has a consistent trajectory (:meth:`Trajectory.check`) with finite positions
    and series, or features; a failed result gives a reason; ``RunStats`` names this simulator and its
    ``version``, and its ``preset``/``backend`` equal the config's ``preset``/``backend`` fields when the
    config has them (they are part of a run's stored identity).
    """
    space = sim.parameter_space()
    if space.dim == 0:
        raise _fail(sim, "parameter_space() has no parameters")
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
                _check_trajectory(sim, t)
        elif not res.failure:
            raise _fail(sim, f"failed result {i} must give a failure reason")
        _check_stats(sim, res)
    return results


def _check_trajectory(sim: Any, t: Trajectory) -> None:
    if not isinstance(t, Trajectory):
        raise _fail(sim, f"trajectory must be an invphys.core.results.Trajectory, got {type(t).__name__}")
    try:
        t.check()
    except ValueError as exc:
        raise _fail(sim, str(exc)) from None
    if not t.series and not t.has_particles:
        raise _fail(sim, "an ok run's trajectory holds neither time series nor particle positions")
    if t.positions is not None and not np.isfinite(t.positions).all():
        raise _fail(sim, "an ok run has non-finite positions (report it as failed instead)")
    for name, s in t.series.items():
        if not np.isfinite(np.asarray(s.values, dtype=np.float64)).all():
            raise _fail(sim, f"series {name!r} of an ok run is non-finite (report the run as failed instead)")


def _check_stats(sim: Simulator, res: SimulationResult) -> None:
    st = res.stats
    if st.simulator != sim.name:
        raise _fail(sim, f"RunStats.simulator is {st.simulator!r}, expected the plugin name {sim.name!r}")
    if st.simulator_version != str(sim.version):
        raise _fail(sim, f"RunStats.simulator_version is {st.simulator_version!r}, expected {sim.version!r}")
    for key in ("preset", "backend"):
        configured = getattr(sim.config, key, None)
        if configured is not None and getattr(st, key) != str(configured):
            raise _fail(sim, f"RunStats.{key} is {getattr(st, key)!r} but the config's {key} is "
                             f"{configured!r} (they must agree: both are part of a run's identity)")


def check_deterministic(sim: Simulator, n_runs: int = 2, seed: int = 1) -> None:
    """Simulating the same parameters twice, and in another batch order, gives the same results.

    Datasets key a run by (identity, parameters) and never re-run it, so a simulator must be
    deterministic for a given config (or document that it is not).
    """
    space = sim.parameter_space()
    params = space.denormalize(np.random.default_rng(seed).uniform(0, 1, size=(n_runs, space.dim)))
    first = sim.simulate(params)
    second = sim.simulate(params[::-1])[::-1]
    for i, (a, b) in enumerate(zip(first, second, strict=True)):
        if a.ok != b.ok:
            raise _fail(sim, f"row {i}: ok={a.ok} once and ok={b.ok} on a repeat")
        if not a.ok or a.trajectory is None or b.trajectory is None:
            continue
        ta, tb = a.trajectory, b.trajectory
        if set(ta.series) != set(tb.series):
            raise _fail(sim, f"row {i}: series names differ between repeats")
        for name in ta.series:
            if not np.array_equal(ta.series[name].values, tb.series[name].values):
                raise _fail(sim, f"row {i}: series {name!r} differs between repeats")
        if ta.positions is not None and not np.array_equal(ta.positions, tb.positions):
            raise _fail(sim, f"row {i}: positions differ between repeats")


def check_trajectory_file(traj: Trajectory, tmp_dir: Any) -> Trajectory:
    """The framework's trajectory file keeps ``traj``'s series, particle arrays and array extras."""
    from invphys.core.trajectory_io import load_trajectory, save_trajectory

    back = load_trajectory(save_trajectory(traj, Path(tmp_dir) / "conformance_trajectory.npz"))
    for name, s in traj.series.items():
        got = back.series.get(name)
        if got is None or not (np.array_equal(got.times, s.times) and np.array_equal(got.values, s.values)):
            raise _fail(traj, f"series {name!r} did not survive the trajectory file")
        if got.unit != s.unit:
            raise _fail(traj, f"series {name!r} lost its unit")
    for key in ("positions", "damage", "labels", "frame_indices"):
        a, b = getattr(traj, key), getattr(back, key)
        if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
            raise _fail(traj, f"{key} did not survive the trajectory file")
    lost = sorted(k for k in traj.extra if k not in back.extra)
    if lost:
        raise _fail(traj, f"extra entries {lost} are neither arrays nor JSON values and are not stored")
    return back


def check_render(sim: Simulator, traj: Trajectory, out_dir: Any, max_frames: int = 2) -> Rendering:
    """``sim.render`` returns a :class:`Rendering`, keeps to ``max_frames`` and writes only under ``out_dir``."""
    out_dir = Path(out_dir)
    done = sim.render(traj, out_dir, max_frames=max_frames, animation="none")
    if not isinstance(done, Rendering):
        raise _fail(sim, f"render must return an invphys.core.results.Rendering, got {type(done).__name__}")
    if not done.images:
        raise _fail(sim, "render wrote no image")
    if len(done.images) > max_frames + 1:
        raise _fail(sim, f"render wrote {len(done.images)} images for max_frames={max_frames} "
                         "(at most max_frames frames plus one summary image)")
    root = out_dir.resolve()
    for p in [*done.images, *done.files, *([done.animation] if done.animation else [])]:
        path = Path(p).resolve()
        if not path.is_file():
            raise _fail(sim, f"render listed {p}, which does not exist")
        if root not in path.parents:
            raise _fail(sim, f"render wrote {p} outside the directory it was given ({out_dir})")
    return done


def check_feature_extractor(extractor: FeatureExtractor, results: list[SimulationResult]) -> np.ndarray:
    """Extract features of the ok results and check shape, names and finiteness."""
    names = extractor.feature_names
    if len(set(names)) != len(names):
        raise _fail(extractor, "feature names must be unique")
    rows = [np.asarray(extractor.extract(r.trajectory), dtype=np.float64)
            for r in results if r.ok and r.trajectory is not None]
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
