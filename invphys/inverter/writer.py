"""Write an inverter bundle from a run's trained parts (the ``train`` and ``invert`` stages call this).

Layout of a bundle::

    manifest.yaml                 format_version, invphys_version, simulator, dataset, parameter_space,
                                  features, components, methods, default_method, files{path: sha256}
    README.md                     what it is, how it was trained, how to use it
    surrogate/                    the surrogate as its plugin saved it (model.json, weights.pt: tensors only)
    latents/<label>/              each latent model, likewise
    policies/<label>/             each goal-conditioned policy or fitted baseline as its plugin saved it
                                  (gc_ppo: gc_ppo.json + policy.npz; npe: npe.json + npe_weights.npz)
    inference/*.npz               verified NumPy forms of the networks (answers without torch)
    data/train.npz, data/test.npz the training and held-out partitions' theta and features

The bundle is assembled in a temporary sibling directory and moved into place, so a reader never
sees half a bundle. No part is a pickle (format 2); :func:`upgrade_bundle` converts a format-1 bundle.
:func:`export_destination` and :func:`copy_bundle` are ``invphys export``: the copy never replaces
anything but a bundle, never the source or what contains it, and is swapped in only once it loads.
"""

from __future__ import annotations

import os
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
    """Everything a bundle is made of (gathered from a run by :func:`invphys.pipeline.artifacts.parts_from_context`)."""

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
    #: the spec's ``default_method`` (used when the bundle ships it; else :func:`default_method` picks)
    default_method: str | None = None


def feature_units(extractor: Any, names: list[str]) -> list[str]:
    """The extractor's unit of each feature (empty strings when it names none, or not one per feature)."""
    units = getattr(extractor, "feature_units", None)
    if isinstance(units, dict):
        return [str(units.get(n, "")) for n in names]
    if isinstance(units, (list, tuple)) and len(units) == len(names):
        return [str(u) for u in units]
    return [""] * len(names)


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
    from invphys.core.version import __version__
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
            "invphys_version": __version__,
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
            "default_method": parts.default_method if parts.default_method in methods else default_method(methods),
        }
        (tmp / README_FILE).write_text(readme(manifest))
        write_manifest(tmp, manifest)
        install_dir(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


def install_dir(tmp: Path, dest: Path) -> None:
    """Move the finished directory ``tmp`` to ``dest`` (a sibling); a previous ``dest`` is moved aside first
    and removed only once the new one is in place (put back if the move fails)."""
    if not dest.exists():
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp.rename(dest)
        return
    old = dest.with_name(f".{dest.name}.old{uuid.uuid4().hex[:6]}")
    dest.rename(old)
    try:
        tmp.rename(dest)
    except BaseException:
        old.rename(dest)
        raise
    shutil.rmtree(old, ignore_errors=True)


# -- export and upgrade ------------------------------------------------------------------------------
def export_destination(src: Path, out: Path, force: bool) -> bool:
    """Check that ``out`` may receive a copy of the bundle ``src``; True when an existing bundle there is to
    be replaced (``force``). Never allowed: ``out`` equal to, inside, or containing the source; inside
    another bundle; under a regular file; a symlink or a symlink loop; an existing file; a non-empty
    directory that is not a bundle (even with ``force``)."""
    from invphys.inverter.manifest import MANIFEST_FILE

    where = f"--out {str(out)!r}"
    try:
        real_out, real_src = Path(os.path.realpath(out, strict=False)), src.resolve(strict=True)
        anc = next((a for a in [out, *out.parents] if os.path.lexists(a)), Path("."))
        if anc.is_symlink() and anc == out:
            raise InvphysError(f"{where} is a symlink; name the directory itself")
        Path(anc).resolve(strict=True)
    except (OSError, RuntimeError) as exc:  # a symlink loop, or a path the system cannot resolve
        raise InvphysError(f"{where}: cannot resolve the path ({getattr(exc, 'strerror', None) or exc})") from None
    if not anc.is_dir():
        raise InvphysError(f"{where}: {str(anc)!r} is a file, not a directory")
    if real_out == real_src or real_src in real_out.parents:
        raise InvphysError(f"{where} is inside the bundle being exported ({src}); name a directory outside it")
    if real_out in real_src.parents:
        raise InvphysError(f"{where} contains the bundle being exported ({src}); replacing it would delete the "
                           f"source: name another directory")
    inside = next((a for a in real_out.parents if (a / MANIFEST_FILE).is_file()), None)
    if inside is not None:
        raise InvphysError(f"{where} is inside the inverter bundle {str(inside)!r}; name a directory outside it")
    if not os.path.lexists(out):
        return False
    if not out.is_dir():
        raise InvphysError(f"{where} exists and is a file; refusing to replace it")
    if not any(out.iterdir()):
        return False
    if not force:
        raise InvphysError(f"{where} exists and is not empty; pass --force to replace the bundle there")
    if not (out / MANIFEST_FILE).is_file():
        raise InvphysError(f"{where} is not an inverter bundle; refusing to replace it")
    return True


def copy_bundle(src: Path, out: Path, files: Any) -> Path:
    """Copy the manifest and the listed ``files`` of the bundle ``src`` to ``out`` through a temporary sibling
    (a failed copy leaves ``out`` as it was); the copy must load before it replaces anything."""
    from invphys.inverter.bundle import Bundle
    from invphys.inverter.manifest import MANIFEST_FILE

    def fill(tmp: Path) -> None:
        shutil.copy2(src / MANIFEST_FILE, tmp / MANIFEST_FILE)
        for rel in files:
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / rel, tmp / rel)
        Bundle(tmp)  # the copy verifies

    return _build_then_install(out, fill)


def _build_then_install(out: Path, fill: Any) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp{uuid.uuid4().hex[:6]}")
    tmp.mkdir()
    try:
        fill(tmp)
        install_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def upgrade_bundle(src: Path, out: Path, trust_pickles: bool, registry: Any = None) -> dict[str, Any]:
    """Write the format-1 bundle ``src`` as a current one at ``out``: each pickled part (an NPE posterior's
    ``npe.pt``, a PPO policy's ``policy.zip``) is loaded once through its plugin's ``load_legacy_pickle`` --
    which RUNS CODE stored in the file, hence ``trust_pickles`` -- and saved as tensors; the converted part
    must answer exactly as the pickled one. Returns {label: what was converted}."""
    from invphys.inverter.manifest import LEGACY_PICKLES, BundleError, read_manifest

    manifest = read_manifest(src, verify=True, allow_legacy=True)
    legacy = {rel.rsplit("/", 1)[0]: rel for rel in manifest["files"] if rel.rsplit("/", 1)[-1] in LEGACY_PICKLES}
    if legacy and not trust_pickles:
        raise BundleError(f"bundle {str(src)!r} holds pickled parts ({', '.join(sorted(legacy.values()))}); "
                          f"converting them runs code stored in them: pass --trust-pickles only if you trust "
                          f"where the bundle came from")
    owners = {entry.get("path"): label for label, entry in manifest["methods"].items()}
    unknown = sorted(d for d in legacy if d not in owners)
    if unknown:
        raise BundleError(f"bundle {str(src)!r}: {legacy[unknown[0]]} belongs to no method; cannot convert it")
    if registry is None:
        from invphys import registry as reg_module

        registry = reg_module.default_registry()
    converted: dict[str, str] = {}

    def fill(tmp: Path) -> None:
        from invphys.inverter.bundle import Bundle

        for rel in manifest["files"]:
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / rel, tmp / rel)
        for directory, rel in sorted(legacy.items()):
            label = owners[directory]
            cls = registry.get("optimizer", manifest["methods"][label]["type"])
            if not hasattr(cls, "load_legacy_pickle"):
                raise BundleError(f"bundle {str(src)!r}: {rel} has no converter in plugin {cls.name!r}")
            old = cls.load_legacy_pickle(tmp / directory)
            old.save(tmp / directory)
            _same_answers(old, cls.load(tmp / directory), src / "data" / "test.npz", rel)
            converted[label] = f"{rel} -> {', '.join(sorted(p.name for p in (tmp / directory).iterdir()))}"
        write_manifest(tmp, {**manifest, "format_version": FORMAT_VERSION,
                             "upgraded": {"from_format": 1, "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                                          "converted": sorted(legacy.values())}})
        Bundle(tmp)  # the converted bundle loads

    _build_then_install(out, fill)
    return converted


def _same_answers(old: Any, new: Any, data: Path, rel: str) -> None:
    """Refuse a conversion whose tensors do not reproduce the pickled part exactly (same seed)."""
    from invphys.inverter.manifest import BundleError

    if hasattr(old, "posterior_samples"):
        with np.load(data, allow_pickle=False) as z:
            y = z["y"][:4]
        a, b = old.posterior_samples(y), new.posterior_samples(y)
    elif getattr(old, "model", None) is not None and hasattr(old.model, "predict"):
        obs = np.random.default_rng(0).normal(0, 1, (32, old.model.observation_space.shape[0])).astype(np.float32)
        a, b = (old.model.predict(obs, deterministic=True)[0],), (new.model.predict(obs, deterministic=True)[0],)
    else:
        return
    if not all(np.array_equal(x, z, equal_nan=True) for x, z in zip(a, b, strict=True)):
        raise BundleError(f"converting {rel}: the tensor copy does not answer exactly as the pickled part; "
                          f"nothing was written")


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
