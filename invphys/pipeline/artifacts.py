"""What the pipeline's stages build alike from a :class:`StageContext`: the inverter bundle's parts
(:func:`parts_from_context`) and the bundle itself (:func:`write_inverter`, by the train and invert stages),
the map from unit-cube to physical parameters (:func:`to_params`) and the spec's named objectives
(:func:`objectives`). Stages import these from here instead of from one another; the files one stage
writes for another are read through :mod:`invphys.pipeline.stage_files`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.inverter.writer import BundleParts, feature_units

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext


def to_params(ctx: StageContext) -> Any:
    """unit-cube rows -> physical parameter lists (NaNs when the simulator cannot be built here)."""
    try:
        space = ctx.simulator().parameter_space()
    except Exception:  # a simulator that cannot be built here: physical values unknown
        return lambda theta: [float("nan")] * len(theta)
    return lambda theta: space.denormalize(np.asarray(theta)).tolist()


def objectives(ctx: StageContext) -> dict[str, Any]:
    """The spec's named weighted objectives, with percentiles from the training partition."""
    from invphys.core.objectives import WeightedObjective

    data = ctx.dataset()
    train_idx, _ = ctx.split()
    return {label: WeightedObjective.from_names(sec.weights, data.feature_names, data.y[train_idx], name=label)
            for label, sec in ctx.spec.objectives.items()}


def write_inverter(ctx: StageContext, with_policies: bool) -> str:
    """Write the run's inverter bundle to ``OUT/inverter/`` (the invert stage adds its policies)."""
    from invphys.inverter.writer import BUNDLE_DIR, write_bundle

    path = write_bundle(parts_from_context(ctx, with_policies=with_policies), ctx.out / BUNDLE_DIR)
    ctx.log(f"inverter bundle written to {path}")
    return str(path)


def parts_from_context(ctx: StageContext, with_policies: bool) -> BundleParts:
    """Gather a run's parts through its stage context (``with_policies`` after the invert stage)."""
    from invphys.core.spec import optimizer_plugin_block
    from invphys.plugins.baselines import learns_from_rows

    spec, reg = ctx.spec, ctx.registry
    data = ctx.dataset()
    train_idx, test_idx = ctx.split()
    sim_info = reg.info("simulator", spec.simulator["type"])
    try:
        extractor = ctx.extractor()
        extractor_block = ctx.extractor_block()
    except InvphysError:
        extractor, extractor_block = None, {}
    names = list(data.feature_names)
    train_dir = ctx.stage_dir_of("train")
    if spec.surrogate is None:
        raise InvphysError("an inverter bundle needs the spec's surrogate")
    sur_type = spec.surrogate["type"]
    latents = {label: (block["type"], ctx.latent(label), train_dir / "latent" / label)
               for label, block in spec.latent_models.items()}
    methods: dict[str, dict[str, Any]] = {}
    policies: dict[str, tuple[Any, Path]] = {}
    heldout = _heldout(ctx) if with_policies else {}
    for label, block in spec.optimizers.items():
        plugin_block = optimizer_plugin_block(block)
        cls = reg.get("optimizer", block["type"])
        entry = {"type": block["type"], "kind": "policy" if getattr(cls, "goal_conditioned", False) else "optimizer",
                 "space": block.get("space", "raw"), "evaluator": block.get("evaluator", "shared"),
                 "config": {k: v for k, v in plugin_block.items() if k != "type"}}
        lam = float(block.get("uncertainty_penalty", 0.0) or 0.0)
        if lam > 0:  # the invert stage scores with R - lambda x std: the bundle's method answers alike
            entry["uncertainty_penalty"] = lam
        if label in heldout:
            entry["heldout"] = heldout[label]
        if entry["kind"] == "policy":
            saved = ctx.stage_dir_of("invert") / "policies" / label
            if with_policies and saved.is_dir() and hasattr(cls, "load"):
                policies[label] = (cls.load(saved), saved)  # trained policies and fitted dataset baselines
            elif not (with_policies and learns_from_rows(cls)):
                continue  # not trained yet (train stage) or not persistable; a baseline refits from the bundle's rows
        methods[label] = entry
    methods.update(refine_methods(spec, methods))
    methods.update(pool_methods(spec, methods))
    return BundleParts(
        name=spec.name, description=spec.description, simulator_block=dict(spec.simulator),
        simulator_version=_data_version(ctx) or str(getattr(sim_info.cls, "version", "")),
        simulator_distribution=sim_info.distribution,
        parameter_space=ctx.simulator().parameter_space(), feature_names=names,
        feature_units=feature_units(extractor, names), extractor_block=extractor_block, scales=ctx.scales(),
        train=(data.theta[train_idx], data.y[train_idx]), test=(data.theta[test_idx], data.y[test_idx]),
        dataset={"fingerprint": data.fingerprint, "n_rows": len(data.theta), "n_train": len(train_idx),
                 "n_test": len(test_idx), "path": str(ctx.dataset_path()),
                 "test_fraction": spec.dataset.test_fraction, "split_seed": spec.seed},
        surrogate=(sur_type, ctx.surrogate(), train_dir / "surrogate"), latents=latents, methods=methods,
        policies=policies, seed=spec.seed, default_method=spec.default_method)


def pool_config(label: str, block: dict[str, Any]) -> dict[str, Any]:
    """A spec pool's manifest config, its settings checked as :class:`~invphys.inverter.pool.PoolSettings`
    (one clear error naming the pool otherwise)."""
    from invphys.inverter.pool import PoolSettings

    config = dict(block)  # `extra` is a list: the spec's validation made it one
    try:
        PoolSettings(**{k: v for k, v in config.items() if k != "posterior"}).checked()
    except TypeError:
        unknown = sorted(set(config) - {"posterior", *PoolSettings.__dataclass_fields__})
        raise InvphysError(f"pools.{label}: unknown setting(s) {', '.join(unknown)}; settings: posterior, "
                           f"{', '.join(PoolSettings.__dataclass_fields__)}") from None
    except InvphysError as exc:
        raise InvphysError(f"pools.{label}: {exc}") from None
    return config


def check_pools(spec: Any) -> None:
    """Raise :class:`InvphysError` for the first of the spec's pools with a bad setting (before any stage runs)."""
    for label, block in (getattr(spec, "pools", None) or {}).items():
        pool_config(label, block)


def pool_methods(spec: Any, methods: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The spec's ``pools`` as manifest entries, each once every method it draws from is in ``methods``."""
    out: dict[str, dict[str, Any]] = {}
    for label, block in (getattr(spec, "pools", None) or {}).items():
        config = pool_config(label, block)
        if all(m in methods for m in [config["posterior"], *config.get("extra", [])]):
            out[label] = {"type": "pool", "kind": "pool", "space": "raw", "evaluator": "shared", "config": config}
    return out


def refine_methods(spec: Any, methods: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The spec's ``evaluation.methods`` that a bundle can answer: CMA-ES on the surrogate (optionally
    uncertainty-penalised) from the answer of a method the bundle ships (``start``), as manifest entries
    (plain settings; the validate stage refines alike). Methods with the simulator in the loop, or whose
    start the bundle does not ship (a dataset baseline of the evaluation section), are left out."""
    out: dict[str, dict[str, Any]] = {}
    ev = getattr(spec, "evaluation", None)
    for label, method in (getattr(ev, "methods", None) or {}).items():
        if method.evaluator != "surrogate" or method.start not in methods or label in methods:
            continue
        entry: dict[str, Any] = {"type": "cma_es", "kind": "optimizer", "space": "raw", "evaluator": "shared",
                                 "config": {"budget": int(method.budget), "popsize": int(method.popsize),
                                            "sigma0": float(method.sigma0)},
                                 "start": method.start}
        if method.uncertainty_penalty > 0:
            entry["uncertainty_penalty"] = float(method.uncertainty_penalty)
        out[label] = entry
    return out


def _data_version(ctx: StageContext) -> str | None:
    """The simulator version the dataset was generated with (what the bundle was trained on)."""
    from invphys.core.dataset import DatasetStore

    try:
        identity = DatasetStore(ctx.dataset_path()).metadata.get("identity") or {}
    except Exception:  # a store without readable metadata: fall back to the installed version
        return None
    return str(identity["version"]) if identity.get("version") else None


def _heldout(ctx: StageContext) -> dict[str, dict[str, Any]]:
    """Per optimiser label: mean R_surr, evaluations and time on the run's held-out targets."""
    import json

    path = ctx.stage_dir_of("invert") / "results.json"
    if not path.is_file():
        return {}
    rows = [r for r in json.loads(path.read_text()) if r.get("problem") == "target"]
    out = {}
    for label in dict.fromkeys(r["optimizer"] for r in rows):
        mine = [r for r in rows if r["optimizer"] == label]
        out[label] = {"targets": len(mine),
                      "mean_r_surrogate": round(float(np.mean([r["r_surrogate"] for r in mine])), 4),
                      "mean_evaluations": float(np.mean([r["evaluations"] for r in mine])),
                      "mean_time_s": round(float(np.mean([r["wall_time_s"] for r in mine])), 5)}
    return out
