"""Write an inverter bundle from a run's trained parts (the ``train`` and ``invert`` stages call this).

Layout of a bundle::

    manifest.yaml                 format_version, invphys_version, simulator, dataset, parameter_space,
                                  features, components, methods, default_method, files{path: sha256}
    README.md                     what it is, how it was trained, how to use it
    surrogate/                    the surrogate as its plugin saved it (model.json, weights.pt)
    latents/<label>/              each latent model, likewise
    policies/<label>/             each goal-conditioned policy as its plugin saved it (gc_ppo: policy.zip)
    inference/*.npz               verified NumPy forms of the networks (answers without torch)
    data/train.npz, data/test.npz the training and held-out partitions' theta and features

The bundle is assembled in a temporary sibling directory and moved into place, so a reader never
sees half a bundle.
"""

from __future__ import annotations

import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.inverter.manifest import FORMAT_VERSION, sha256_json, system_info, write_manifest

README_FILE = "README.md"
#: where a run directory keeps its bundle
BUNDLE_DIR = "inverter"


@dataclass
class BundleParts:
    """Everything a bundle is made of (gathered from a run by :func:`parts_from_context`)."""

    name: str
    description: str
    simulator_block: dict[str, Any]
    simulator_version: str
    simulator_distribution: str
    parameter_space: Any  # ParameterSpace
    feature_names: list[str]
    feature_units: list[str]
    extractor_block: dict[str, Any]
    scales: np.ndarray
    train: tuple[np.ndarray, np.ndarray]
    test: tuple[np.ndarray, np.ndarray]
    dataset: dict[str, Any]
    surrogate: tuple[str, Any, Path]  # (type, model, saved directory)
    latents: dict[str, tuple[str, Any, Path]] = field(default_factory=dict)
    methods: dict[str, dict[str, Any]] = field(default_factory=dict)
    policies: dict[str, tuple[Any, Path]] = field(default_factory=dict)  # label -> (plugin, saved dir)
    seed: int = 0
    notes: str = ""


def _units(extractor: Any, names: list[str]) -> list[str]:
    units = getattr(extractor, "feature_units", None)
    if isinstance(units, dict):
        return [str(units.get(n, "")) for n in names]
    if isinstance(units, (list, tuple)) and len(units) == len(names):
        return [str(u) for u in units]
    return [""] * len(names)


def parts_from_context(ctx: Any, with_policies: bool) -> BundleParts:
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
        if label in heldout:
            entry["heldout"] = heldout[label]
        if entry["kind"] == "policy":
            saved = ctx.stage_dir_of("invert") / "policies" / label
            if with_policies and saved.is_dir() and hasattr(cls, "load"):
                policies[label] = (cls.load(saved), saved)  # trained policies and fitted dataset baselines
            elif not (with_policies and learns_from_rows(cls)):
                continue  # not trained yet (train stage) or not persistable; a baseline refits from the bundle's rows
        methods[label] = entry
    return BundleParts(
        name=spec.name, description=spec.description, simulator_block=dict(spec.simulator),
        simulator_version=_data_version(ctx) or str(getattr(sim_info.cls, "version", "")),
        simulator_distribution=sim_info.distribution,
        parameter_space=ctx.simulator().parameter_space(), feature_names=names,
        feature_units=_units(extractor, names), extractor_block=extractor_block, scales=ctx.scales(),
        train=(data.theta[train_idx], data.y[train_idx]), test=(data.theta[test_idx], data.y[test_idx]),
        dataset={"fingerprint": data.fingerprint, "n_rows": len(data.theta), "n_train": len(train_idx),
                 "n_test": len(test_idx), "path": str(ctx.dataset_path()),
                 "test_fraction": spec.dataset.test_fraction, "split_seed": spec.seed},
        surrogate=(sur_type, ctx.surrogate(), train_dir / "surrogate"), latents=latents, methods=methods,
        policies=policies, seed=spec.seed)


def _data_version(ctx: Any) -> str | None:
    """The simulator version the dataset was generated with (what the bundle was trained on)."""
    from invphys.core.dataset import DatasetStore

    try:
        identity = DatasetStore(ctx.dataset_path()).metadata.get("identity") or {}
    except Exception:  # a store without readable metadata: fall back to the installed version
        return None
    return str(identity["version"]) if identity.get("version") else None


def _heldout(ctx: Any) -> dict[str, dict[str, Any]]:
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


def default_method(methods: dict[str, dict[str, Any]]) -> str | None:
    """The best amortised method: the goal-conditioned policy with the highest held-out R_surr on the
    shared surrogate (then any policy, then the best optimiser)."""
    def score(label: str) -> float:
        return float(methods[label].get("heldout", {}).get("mean_r_surrogate", -1.0))

    for pool in ([k for k, m in methods.items() if m["kind"] == "policy" and m["evaluator"] == "shared"],
                 [k for k, m in methods.items() if m["kind"] == "policy"], list(methods)):
        if pool:
            return max(pool, key=score)
    return None


def write_bundle(parts: BundleParts, dest: str | Path) -> Path:
    """Assemble the bundle from ``parts`` and move it to ``dest`` (replacing a previous bundle there)."""
    import invphys
    from invphys.inverter import export

    dest = Path(dest)
    tmp = dest.with_name(f".{dest.name}.tmp{uuid.uuid4().hex[:6]}")
    tmp.mkdir(parents=True)
    try:
        space = parts.parameter_space
        d, m = space.dim, len(parts.feature_names)
        components: dict[str, Any] = {}
        sur_type, sur, sur_dir = parts.surrogate
        shutil.copytree(sur_dir, tmp / "surrogate")
        components["surrogate"] = {"type": sur_type, "path": "surrogate",
                                   "inference": _save(export.surrogate_program(sur, d, parts.seed),
                                                      tmp, "inference/surrogate.npz")}
        components["latents"] = {}
        for label, (typ, lat, lat_dir) in parts.latents.items():
            shutil.copytree(lat_dir, tmp / "latents" / label)
            components["latents"][label] = {
                "type": typ, "path": f"latents/{label}", "latent_dim": int(lat.latent_dim),
                "bound": float(lat.latent_bound),
                "decoder": _save(export.decoder_program(lat, parts.seed), tmp, f"inference/latent_{label}_decoder.npz"),
                "head": _save(export.head_program(lat, parts.seed), tmp, f"inference/latent_{label}_head.npz")}
        methods = {k: dict(v) for k, v in parts.methods.items()}
        for label, (plugin, saved) in parts.policies.items():
            shutil.copytree(saved, tmp / "policies" / label)
            entry = methods[label]
            entry["path"] = f"policies/{label}"
            meta, cfg = getattr(plugin, "meta", {}), plugin.config
            if meta and hasattr(plugin, "model"):
                entry["rollout"] = {"horizon": int(cfg.horizon), "step_scale": float(cfg.step_scale),
                                    "kappa": float(cfg.kappa), "space": meta["space"],
                                    "feature_mean": meta["feature_mean"], "feature_std": meta["feature_std"],
                                    "start": meta["start"], "start_features": meta["start_features"]}
                obs_dim = int(meta["space"]["dim"]) + 2 * m + 2
                actor = export.actor_program(plugin.model, obs_dim, parts.seed)
                if actor is not None:
                    prog, log_std = actor
                    prog.arrays["log_std"] = log_std
                    entry["inference"] = _save(prog, tmp, f"inference/policy_{label}.npz")
            entry["metrics"] = _plain(getattr(plugin, "metrics", {}))
        (tmp / "data").mkdir()
        for split, (theta, y) in (("train", parts.train), ("test", parts.test)):
            np.savez_compressed(tmp / "data" / f"{split}.npz", theta=theta, y=y)
        y_train = parts.train[1]
        from invphys.core.objectives import feature_standardiser

        mean, std = feature_standardiser(y_train)
        manifest: dict[str, Any] = {
            "format_version": FORMAT_VERSION,
            "invphys_version": invphys.__version__,
            "bundle_id": uuid.uuid4().hex[:12],
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "name": parts.name, "description": parts.description, "notes": parts.notes,
            "system_info": system_info(),
            "simulator": {"name": parts.simulator_block["type"], "version": parts.simulator_version,
                          "distribution": parts.simulator_distribution, "config": parts.simulator_block,
                          "config_sha256": sha256_json(parts.simulator_block)},
            "dataset": {**parts.dataset, "space_sha256": sha256_json(space.describe())},
            "parameter_space": {"names": list(space.names), "units": [p.unit for p in space.parameters],
                                "low": [p.low for p in space.parameters], "high": [p.high for p in space.parameters],
                                "log_scale": [bool(p.log) for p in space.parameters],
                                "descriptions": [p.description for p in space.parameters]},
            "features": {"names": parts.feature_names, "units": parts.feature_units,
                         "extractor": parts.extractor_block, "scales": _floats(parts.scales),
                         "mean": _floats(mean), "std": _floats(std), "train_min": _floats(y_train.min(axis=0)),
                         "train_max": _floats(y_train.max(axis=0)), "kappa": 3.0},
            "components": components,
            "methods": methods,
            "default_method": default_method(methods),
        }
        (tmp / README_FILE).write_text(readme(manifest))
        write_manifest(tmp, manifest)
        if dest.exists():
            old = dest.with_name(f".{dest.name}.old{uuid.uuid4().hex[:6]}")
            dest.rename(old)
            tmp.rename(dest)
            shutil.rmtree(old, ignore_errors=True)
        else:
            dest.parent.mkdir(parents=True, exist_ok=True)
            tmp.rename(dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


def _save(program: Any, root: Path, rel: str) -> str | None:
    if program is None:
        return None
    program.save(root / rel)
    return rel


def _floats(a: Any) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)]


def _plain(obj: Any) -> Any:
    """JSON/YAML-safe copy (numpy scalars and arrays to Python)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def readme(manifest: dict[str, Any]) -> str:
    """The bundle's README: what it inverts, how it was made, how to use it."""
    ps, feats, sim = manifest["parameter_space"], manifest["features"], manifest["simulator"]
    lines = [f"# Inverter bundle: {manifest['name']}", "",
             manifest.get("description") or "", "",
             f"Made by invphys {manifest['invphys_version']} on {manifest['created_utc']} from "
             f"{manifest['dataset']['n_rows']} simulations of `{sim['name']}` {sim['version']} "
             f"(dataset fingerprint `{manifest['dataset']['fingerprint']}`).", ""]
    if manifest.get("notes"):
        lines += [manifest["notes"], ""]
    lines += ["Use it:", "", "```bash", "invphys invert . --feature NAME=VALUE ... --json", "```", "",
              "```python", "import invphys", "inv = invphys.load_inverter('PATH/TO/THIS/FOLDER')",
              "result = inv.invert({...})  # features by name", "print(result.parameters)", "```", "",
              "## Parameters", "", "| name | unit | low | high | log |", "|---|---|---|---|---|"]
    for i, n in enumerate(ps["names"]):
        lines.append(f"| {n} | {ps['units'][i]} | {ps['low'][i]:g} | {ps['high'][i]:g} | {ps['log_scale'][i]} |")
    lines += ["", "## Features (targets are given by these names)", "",
              "| name | unit | training range |", "|---|---|---|"]
    for i, n in enumerate(feats["names"]):
        lines.append(f"| {n} | {feats['units'][i]} | {feats['train_min'][i]:.4g} .. {feats['train_max'][i]:.4g} |")
    lines += ["", "## Methods", "", f"Default: `{manifest['default_method']}`.", "",
              "| method | type | space | held-out mean R_surr | evaluations |", "|---|---|---|---|---|"]
    for label, m in manifest["methods"].items():
        h = m.get("heldout", {})
        r = h.get("mean_r_surrogate")
        ev = h.get("mean_evaluations")
        lines.append(f"| {label} | {m['type']} | {m['space']} | {'' if r is None else f'{r:.3f}'} | "
                     f"{'' if ev is None else f'{ev:g}'} |")
    return "\n".join(lines) + "\n"
