"""``invphys/Inversion-v0``: inverse design as a Gymnasium environment, from a surrogate or a bundle.

Any RL library can train on an invphys problem::

    import gymnasium as gym
    import invphys.envs  # registers the ids

    env = gym.make("invphys/Inversion-v0", surrogate="runs/quickstart/train/surrogate")

An episode refines a point of the search space over ``horizon`` steps towards a goal y* (target
features): action ``a`` in [-1, 1]^dim moves ``s <- clip(s + step_scale * a)``; the observation is
``[s, y_hat, y*, R, t/T]`` (features standardised); the reward is sparse, the best recovery reward
R_gt (paper eq. 1) among the visited states, at the last step. Goals are drawn from the surrogate's
predictions at uniformly random points of the space (so every goal is reachable), or fixed with
``target=`` or ``reset(options={"goal": y})``.

It sits above the inverter (it loads a bundle directory with :func:`invphys.inverter.load_inverter`);
:mod:`invphys.envs` holds the environment classes it builds and registers its Gymnasium id.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.objectives import percentile_scales, recovery_reward
from invphys.core.standardiser import Standardiser
from invphys.envs.single import InverseDesignEnv
from invphys.envs.task import InverseTask

ENV_ID = "invphys/Inversion-v0"


def make_inversion_env(surrogate: Any = None, *, bundle: Any = None, space: str = "raw",
                       target: Any = None, horizon: int = 8, step_scale: float = 0.5, kappa: float | None = None,
                       scales: Any = None, goal_samples: int = 512, goal_seed: int = 0,
                       parameters: Any = None, render_mode: str | None = None) -> InverseDesignEnv:
    """The environment behind :data:`ENV_ID` (``gym.make`` passes its keyword arguments here).

    Args:
        surrogate: a fitted surrogate (anything with ``predict(theta) -> features``) or the directory of
            a saved one (``OUT/train/surrogate``).
        bundle: instead of ``surrogate``, an inverter bundle: its directory (the form that survives
            Gymnasium's copies of ``make`` arguments), a loaded :class:`~invphys.inverter.Inverter` or its
            ``.bundle``; the environment uses its surrogate, feature scales, ``kappa`` and search spaces.
        space: ``"raw"`` ([0, 1]^d) or, with a bundle, a latent model's label (search in its latent box).
        target: fixed goal features (M,) for every episode; default: a goal drawn per episode.
        horizon, step_scale: episode length T and step size.
        kappa, scales: the recovery reward's sharpness and per-feature scales (default: the bundle's,
            else 3.0 and p95 - p5 of the goal samples).
        goal_samples, goal_seed: random points whose predicted features form the goal distribution.
        parameters: the :class:`~invphys.core.params.ParameterSpace` that names the parameters in ``info``
            (default: the bundle's; a bare surrogate's are ``theta_0``, ... in [0, 1]).

    Every ``reset`` and ``step`` returns ``info`` with ``R`` (the state's recovery reward), ``R_best`` (the
    best so far; also as ``score`` and ``best``), ``theta`` (normalised parameters), ``params`` (physical
    values by name) and ``units`` (each parameter's unit).
    """
    if render_mode is not None:
        raise InvphysError(f"{ENV_ID} renders nothing (render_mode must be None, got {render_mode!r})")
    if (surrogate is None) == (bundle is None):
        raise InvphysError(f"{ENV_ID}: pass exactly one of surrogate= (a model or its directory) or bundle=")
    if bundle is not None:
        if isinstance(bundle, str | Path):
            from invphys.inverter import load_inverter

            bundle = load_inverter(bundle)
        loaded = getattr(bundle, "bundle", bundle)
        search, predict, kappa_, scales_ = _from_bundle(loaded, space)
        parameters = parameters if parameters is not None else getattr(loaded, "space", None)
    else:
        if space != "raw":
            raise InvphysError(f"{ENV_ID}: space={space!r} needs a bundle (a surrogate alone searches 'raw')")
        search, predict, kappa_, scales_ = _from_surrogate(surrogate)
    rng = np.random.default_rng(goal_seed)
    goals = np.asarray(predict(search.sample(int(goal_samples), rng)), dtype=np.float64)
    goals = goals[np.all(np.isfinite(goals), axis=1)]
    if len(goals) < 2:
        raise InvphysError(f"{ENV_ID}: the surrogate predicted fewer than 2 finite goal samples")
    stats = Standardiser.fit(goals)
    scale = np.asarray(scales if scales is not None else scales_ if scales_ is not None
                       else percentile_scales(goals), dtype=np.float64).reshape(-1)
    k = float(kappa if kappa is not None else kappa_ if kappa_ is not None else 3.0)
    fixed = None if target is None else np.asarray(target, dtype=np.float64).reshape(-1)
    if scale.shape != (goals.shape[1],) or (fixed is not None and fixed.shape != scale.shape):
        raise InvphysError(f"{ENV_ID}: the surrogate predicts {goals.shape[1]} features; scales/target have "
                           f"{scale.size}/{'-' if fixed is None else fixed.size}")

    def sample_goals(generator: np.random.Generator, n: int) -> np.ndarray:
        if fixed is not None:
            return np.broadcast_to(fixed, (n, fixed.size)).copy()
        return goals[generator.integers(0, len(goals), size=n)]

    task = InverseTask(low=search.low, high=search.high, dim=search.dim, predict=predict,
                       score=lambda y, g: recovery_reward(y, g, scale, k), feature_mean=stats.mean,
                       feature_std=stats.std, horizon=int(horizon), step_scale=float(step_scale),
                       goal_sampler=sample_goals)
    return InverseDesignEnv(task, describe=parameter_describer(search, parameters))


def parameter_describer(search: Any, parameters: Any = None) -> Any:
    """A function of a search point (dim,) giving ``{"theta", "params", "units"}`` for an env's ``info``:
    normalised parameters, physical values by name and units (``parameters`` a ParameterSpace; without
    one, ``theta_<i>`` in [0, 1], unit ``"1"``)."""
    from invphys.core.params import ParameterSpace

    if parameters is not None and not isinstance(parameters, ParameterSpace):
        raise InvphysError(f"{ENV_ID}: parameters= must be an invphys ParameterSpace, got {type(parameters).__name__}")

    def describe(point: np.ndarray) -> dict[str, Any]:
        theta = np.clip(np.asarray(search.to_theta(np.asarray(point, dtype=np.float64)[None, :]),
                                   dtype=np.float64)[0], 0.0, 1.0)
        if parameters is None or parameters.dim != theta.size:
            names = [f"theta_{i}" for i in range(theta.size)]
            return {"theta": theta.tolist(), "params": dict(zip(names, map(float, theta), strict=True)),
                    "units": dict.fromkeys(names, "1")}
        physical = parameters.denormalize(theta)
        return {"theta": theta.tolist(), "params": parameters.to_mapping(physical),
                "units": {p.name: p.unit for p in parameters.parameters}}

    return describe


def _from_surrogate(surrogate: Any) -> tuple[Any, Any, float | None, np.ndarray | None]:
    from invphys.core.spaces import make_predict, raw_space

    if isinstance(surrogate, str | Path):
        surrogate = load_saved_surrogate(surrogate)
    dims = getattr(surrogate, "dims", None)
    if dims is None or not hasattr(surrogate, "predict"):
        raise InvphysError(f"{ENV_ID}: surrogate= needs a fitted surrogate (with predict and dims) or its directory")
    search = raw_space(int(dims[0]))
    return search, make_predict(search, surrogate), None, None


def _from_bundle(bundle: Any, space: str) -> tuple[Any, Any, float | None, np.ndarray | None]:
    from invphys.core.spaces import make_predict

    try:
        search = bundle.search_space(space)
        surrogate = bundle.surrogate
    except AttributeError as exc:
        raise InvphysError(f"{ENV_ID}: bundle= needs a loaded inverter bundle ({exc})") from None
    return search, make_predict(search, surrogate), float(bundle.kappa), np.asarray(bundle.scales)


def load_saved_surrogate(directory: str | Path) -> Any:
    """The surrogate saved in ``directory`` (its ``model.json`` names the plugin)."""
    import json

    from invphys import registry

    meta_path = Path(directory) / "model.json"
    if not meta_path.is_file():
        raise InvphysError(f"no saved surrogate in {directory} (expected model.json)")
    meta = json.loads(meta_path.read_text())
    if meta.get("kind") != "surrogate":
        raise InvphysError(f"{directory} holds a {meta.get('kind')}, not a surrogate")
    return registry.default_registry().get("surrogate", meta["plugin"]).load(directory)
