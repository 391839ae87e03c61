"""A loaded bundle: its manifest, parameter space, features and (lazily) its networks.

Networks are served by their NumPy inference forms when the bundle has them (no torch import) and
otherwise by their plugins' own ``load`` through the registry. :meth:`Bundle.check_installation`
compares the bundle's simulator and features with the installed plugins.

Every part is reached through :meth:`Bundle.part` (a file) or :meth:`Bundle._plugin_load` (a directory):
the path must stay inside the bundle and every file it holds must be listed (hashed) in the manifest;
NumPy files are read with ``allow_pickle=False`` and each network's input and output sizes are checked
on load, so a bad part is one :class:`BundleError` naming it, never a traceback.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.params import Parameter, ParameterSpace
from invphys.inverter.manifest import (
    UPGRADE_HINT,
    BundleError,
    check_covered,
    part_path,
    python_mismatch,
    read_manifest,
    unimported_code_path,
)
from invphys.inverter.numeric import Program


class FastSurrogate:
    """Surrogate predictions from the bundle (NumPy form, else the plugin): ``predict``, with std."""

    def __init__(self, bundle: Bundle) -> None:
        self._bundle = bundle
        rel = bundle.manifest["components"]["surrogate"].get("inference")
        self._program = bundle.program(rel, "the surrogate's NumPy form", bundle.space.dim,
                                       (None, 1, len(bundle.feature_names))) if rel else None

    def members(self, theta: np.ndarray) -> np.ndarray:
        """(K, B, M) member predictions (K = 1 for a single network)."""
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        if self._program is not None:
            return self._program(theta).astype(np.float64)
        model = self._bundle.surrogate_model()
        mean, std = model.predict_with_uncertainty(theta)
        return np.stack([mean - std, mean + std]) if np.any(std) else mean[None]

    def predict(self, theta: np.ndarray) -> np.ndarray:
        return self.members(theta).mean(axis=0)

    def predict_with_uncertainty(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = self.members(theta)
        return k.mean(axis=0), k.std(axis=0)


class FastLatent:
    """A latent model's decoder and head from the bundle (NumPy forms, else the plugin)."""

    def __init__(self, bundle: Bundle, label: str) -> None:
        entry = bundle.manifest["components"]["latents"][label]
        self._bundle, self.label = bundle, label
        self.latent_dim = int(entry["latent_dim"])
        self.latent_bound = float(entry["bound"])
        k, what = self.latent_dim, f"latent model {label!r}"
        self._decoder = bundle.program(entry["decoder"], f"the decoder of {what}", k,
                                       (1, bundle.space.dim)) if entry.get("decoder") else None
        self._head = bundle.program(entry["head"], f"the feature head of {what}", k,
                                    (1, len(bundle.feature_names))) if entry.get("head") else None

    def decode(self, z: np.ndarray) -> np.ndarray:
        if self._decoder is not None:
            return self._decoder(np.atleast_2d(z)).astype(np.float64)
        return self._bundle.latent_model(self.label).decode(z)

    def encode(self, theta: np.ndarray) -> np.ndarray:
        return self._bundle.latent_model(self.label).encode(theta)

    def predict_features(self, z: np.ndarray) -> np.ndarray:
        if self._head is not None:
            return self._head(np.atleast_2d(z)).astype(np.float64)
        return self._bundle.latent_model(self.label).predict_features(z)


class Bundle:
    """The contents of an inverter bundle directory (see :mod:`invphys.inverter.writer`)."""

    def __init__(self, root: str | Path, registry: Any = None, verify: bool = True, allow_legacy: bool = False) -> None:
        self.root = Path(root)
        self.manifest = read_manifest(self.root, verify=verify, allow_legacy=allow_legacy)
        self._registry = registry
        self._cache: dict[str, Any] = {}
        m = self.manifest
        ps = m["parameter_space"]
        try:
            self.space = ParameterSpace(tuple(
                Parameter(n, float(lo), float(hi), log=bool(lg), unit=str(u), description=str(desc))
                for n, lo, hi, lg, u, desc in zip(ps["names"], ps["low"], ps["high"], ps["log_scale"], ps["units"],
                                                  ps.get("descriptions") or [""] * len(ps["names"]), strict=True)))
        except (KeyError, TypeError, ValueError) as exc:
            raise BundleError(f"{self.root}: the manifest's parameter_space is malformed ({exc})") from None
        self._read_features(m["features"])
        self._check_parts()
        self._check_method_configs()
        msg = python_mismatch(m.get("system_info") or {})
        if msg:
            warnings.warn(msg, stacklevel=3)

    def _read_features(self, f: dict[str, Any]) -> None:
        """Names, units, scales (positive), kappa and training range of the features; one line naming the key."""
        self.feature_names: tuple[str, ...] = tuple(f["names"])
        n = len(self.feature_names)
        key = "features.units"
        try:
            self.feature_units: tuple[str, ...] = tuple(str(u) for u in (f.get("units") or [""] * n))
            key = "features.scales"
            self.scales = np.asarray(f["scales"], dtype=np.float64).reshape(n)
            key = "features.kappa"
            self.kappa = float(f.get("kappa", 3.0))
            key = "features.train_min"
            self.train_min = np.asarray(f.get("train_min", [-np.inf] * n), dtype=np.float64).reshape(n)
            key = "features.train_max"
            self.train_max = np.asarray(f.get("train_max", [np.inf] * n), dtype=np.float64).reshape(n)
        except (TypeError, ValueError):
            raise BundleError(f"{self.root / 'manifest.yaml'}: {key} must hold one number per feature "
                              f"({n} features)") from None
        if len(self.feature_units) != n:
            raise BundleError(f"{self.root / 'manifest.yaml'}: features.units must name one unit per feature")
        if not (np.all(np.isfinite(self.scales)) and np.all(self.scales > 0) and np.isfinite(self.kappa)
                and self.kappa > 0):
            raise BundleError(f"{self.root / 'manifest.yaml'}: features.scales and features.kappa must be "
                              f"finite and > 0")

    def _check_parts(self) -> None:
        """Every part the manifest names (components, inference forms, methods' saves) stays inside the
        bundle and is listed in ``files``; a latent entry has its sizes."""
        comps, files = self.manifest["components"], self.manifest["files"]
        parts = [("components.surrogate." + k, comps["surrogate"].get(k)) for k in ("path", "inference")]
        for label, entry in (comps.get("latents") or {}).items():
            try:
                ok = int(entry["latent_dim"]) >= 1 and float(entry["bound"]) > 0
            except (KeyError, TypeError, ValueError):
                ok = False
            if not ok:
                raise BundleError(f"{self.root / 'manifest.yaml'}: components.latents.{label} needs latent_dim "
                                  f">= 1 and bound > 0")
            parts += [(f"components.latents.{label}.{k}", entry.get(k)) for k in ("path", "decoder", "head")]
        for label, entry in self.methods.items():
            if not isinstance(entry.get("config", {}), dict):
                raise BundleError(f"{self.root / 'manifest.yaml'}: methods.{label}.config must be a mapping")
            parts += [(f"methods.{label}.{k}", entry.get(k)) for k in ("path", "inference")]
        for what, rel in parts:
            if rel is not None:
                check_covered(self.root, rel, files, what)

    def _check_method_configs(self) -> None:
        """Each method's config is valid for its (installed) plugin: one line naming the key, not later."""
        from pydantic import ValidationError

        for label, entry in self.methods.items():
            try:
                cls = self.registry.get("optimizer", entry["type"])
            except InvphysError:
                continue  # not installed: using the method says so
            try:
                cls.Config(**entry.get("config", {}))
            except ValidationError as exc:
                err = exc.errors()[0]
                key = ".".join(str(k) for k in err.get("loc", ())) or "config"
                raise BundleError(f"{self.root / 'manifest.yaml'}: methods.{label}.config.{key}: "
                                  f"{err.get('msg', 'invalid')}") from None
            except TypeError as exc:
                raise BundleError(f"{self.root / 'manifest.yaml'}: methods.{label}.config: {exc}") from None

    def part(self, rel: str, what: str) -> Path:
        """The bundle file ``rel`` (inside the bundle and listed in the manifest's files)."""
        return check_covered(self.root, rel, self.manifest["files"], what)

    # -- registry and installation checks ---------------------------------------------------------
    @property
    def registry(self) -> Any:
        if self._registry is None:
            from invphys import registry

            self._registry = registry.default_registry()
        return self._registry

    @property
    def methods(self) -> dict[str, dict[str, Any]]:
        return self.manifest["methods"]

    @property
    def default_method(self) -> str | None:
        return self.manifest.get("default_method")

    def unfitted_method_error(self, label: str, typ: str) -> InvphysError:
        """The one-line refusal of ``method=label``: a trained estimator of type ``typ`` (npe, ...) that the
        bundle does not hold. A bundle is never fitted at answer time (that took about a minute a call): the
        message names the bundle's own fit of that type, else its methods and how to add one."""
        root = str(self.root)
        same = [k for k, m in self.methods.items() if m.get("type") == typ]
        if same:
            return InvphysError(f"method {label!r} is not in bundle {root!r}; its fitted {typ} is "
                                f"{', '.join(same)}: use --method {same[0]}")
        return InvphysError(
            f"method {label!r} needs a fitted {typ} and bundle {root!r} holds none (its methods: "
            f"{', '.join(self.methods) or 'none'}); to add one, list e.g. '{typ}_best64: {{type: {typ}, samples: 64, "
            f"answer: best_surrogate}}' under optimizers in the bundle's spec, then invphys run SPEC --out RUN and "
            f"invphys export RUN --out BUNDLE")

    def check_installation(self, strict: bool = True) -> list[str]:
        """Compare the bundle's simulator version and features with the installed plugins.

        A different simulator version, or an extractor computing other features, raises
        :class:`BundleError` when ``strict`` (else becomes a returned warning). A simulator that is not
        installed is a warning: inversion works, validation and ``--observed`` do not.
        """
        sim = self.manifest["simulator"]
        problems: list[str] = []
        notes: list[str] = []
        if unimported_code_path(sim["name"]):  # importing it would run code the bundle names
            return [f"simulator {sim['name']!r} is a module path that is not imported, so it is not loaded: "
                    f"inversion works, validation does not"]
        try:
            info = self.registry.info("simulator", sim["name"])
        except InvphysError:
            notes.append(f"simulator {sim['name']!r} is not installed: inversion works, validation does not")
            return notes
        installed = str(getattr(info.cls, "version", ""))
        if installed != str(sim.get("version")):
            problems.append(f"bundle {self.root} was trained on simulator {sim['name']} {sim.get('version')}, "
                            f"the installed one is {installed}: retrain the bundle, or load it anyway with --allow-mismatch "
                            f"(Python: strict=False)")
        block = self.manifest["features"].get("extractor") or {}
        if block.get("type") and not problems and not unimported_code_path(block.get("type")):
            try:
                names = tuple(self.registry.create("feature_extractor", block).feature_names)
            except Exception as exc:  # a plugin failing to build is reported, not fatal here
                notes.append(f"feature extractor {block['type']!r} unavailable ({exc})")
            else:
                if names != self.feature_names:
                    added = [n for n in names if n not in self.feature_names]
                    gone = [n for n in self.feature_names if n not in names]
                    problems.append(f"bundle {self.root} predicts other features than the installed extractor "
                                    f"computes (new: {', '.join(added) or '-'}; gone: {', '.join(gone) or '-'}; "
                                    f"or reordered): retrain the bundle, or load it anyway with --allow-mismatch")
        if problems and strict:
            raise BundleError(problems[0])
        return problems + notes

    # -- components -------------------------------------------------------------------------------
    def _plugin_load(self, kind: str, entry: dict[str, Any]) -> Any:
        """A component's plugin ``load`` on its directory, after checking that every file there is listed
        and that no ``.npz`` in it holds pickled objects; an older pickled save is refused with the
        upgrade command."""
        from invphys.models.base import LegacyPickleError

        cls = self.registry.get(kind, entry["type"])
        what = f"{kind} {entry['type']!r}"
        if not isinstance(entry.get("path"), str):
            raise BundleError(f"bundle {str(self.root)!r}: {what} has no saved path in the manifest")
        directory = check_covered(self.root, entry["path"], self.manifest["files"], what)
        for f in sorted(directory.rglob("*.npz")) if directory.is_dir() else []:
            self._npz(f.relative_to(self.root).as_posix(), what)
        try:
            return cls.load(directory)
        except LegacyPickleError as exc:
            rel = Path(exc.path).relative_to(self.root).as_posix() if self.root in Path(exc.path).parents else exc.path
            raise BundleError(f"bundle {str(self.root)!r} holds {rel}, a pickled part written by an older invphys: "
                              f"loading it would run code stored in the file, so it is refused; "
                              + UPGRADE_HINT.format(root=str(self.root))) from None

    def surrogate_model(self) -> Any:
        """The surrogate plugin itself (torch), loaded on first use."""
        if "surrogate_model" not in self._cache:
            self._cache["surrogate_model"] = self._plugin_load("surrogate", self.manifest["components"]["surrogate"])
        return self._cache["surrogate_model"]

    def latent_model(self, label: str) -> Any:
        key = f"latent_model:{label}"
        if key not in self._cache:
            self._cache[key] = self._plugin_load("latent_model", self._latent_entry(label))
        return self._cache[key]

    def _latent_entry(self, label: str) -> dict[str, Any]:
        latents = self.manifest["components"].get("latents") or {}
        if label not in latents:
            raise BundleError(f"bundle {self.root} has no latent model {label!r} (has: {', '.join(latents) or 'none'})")
        return latents[label]

    @property
    def surrogate(self) -> FastSurrogate:
        if "surrogate" not in self._cache:
            self._cache["surrogate"] = FastSurrogate(self)
        return self._cache["surrogate"]

    def latent(self, label: str) -> FastLatent:
        key = f"latent:{label}"
        if key not in self._cache:
            self._latent_entry(label)
            self._cache[key] = FastLatent(self, label)
        return self._cache[key]

    def search_space(self, label: str) -> Any:
        """The raw box or a latent model's box (a :class:`~invphys.core.interfaces.SearchSpace`)."""
        from invphys.core.spaces import latent_space, raw_space

        key = f"space:{label}"
        if key not in self._cache:
            self._cache[key] = raw_space(self.space.dim) if label == "raw" else latent_space(self.latent(label), name=label)
        return self._cache[key]

    def predictor(self, space_label: str, evaluator: str = "shared") -> Callable[[np.ndarray], np.ndarray]:
        """Features (B, M) of points (B, dim) of a search space, on the shared surrogate or a latent head."""
        from invphys.core.spaces import make_predict

        space = self.search_space(space_label)
        latent = None if space_label == "raw" else self.latent(space_label)
        return make_predict(space, self.surrogate, latent, evaluator)

    def data(self, split: str = "train") -> tuple[np.ndarray, np.ndarray]:
        """(theta, y) of the bundle's training or held-out partition."""
        key = f"data:{split}"
        if key not in self._cache:
            rel = f"data/{split}.npz"
            if not part_path(self.root, rel, f"the {split} data").is_file():
                raise BundleError(f"bundle {self.root} has no {split} data ({split}.npz)")
            arrays = self._npz(self.part(rel, f"the {split} data").relative_to(self.root).as_posix(),
                               f"the {split} data")
            theta, y = arrays.get("theta"), arrays.get("y")
            d, m = self.space.dim, len(self.feature_names)
            if theta is None or y is None or theta.ndim != 2 or y.ndim != 2 or theta.shape[1] != d \
                    or y.shape[1] != m or len(theta) != len(y) or theta.dtype.kind != "f" or y.dtype.kind != "f":
                raise BundleError(f"bundle {str(self.root)!r}: {rel} does not fit the bundle (needs float arrays "
                                  f"theta (N, {d}) and y (N, {m}))")
            self._cache[key] = (theta.astype(np.float64), y.astype(np.float64))
        return self._cache[key]

    def _npz(self, rel: str, what: str) -> dict[str, np.ndarray]:
        """Every array of the bundle's ``.npz`` file ``rel``, read without pickles (else a BundleError)."""
        from invphys.core.safe_read import UserFileError, load_user_npz

        path = self.part(rel, what)
        try:
            arrays = load_user_npz(path, what=what)
        except UserFileError as exc:
            raise BundleError(f"bundle {str(self.root)!r}: {rel} ({what}) is not a NumPy archive invphys loads "
                              f"without running code ({exc.problem})") from None
        bad = [k for k, v in arrays.items() if v.dtype.kind not in "fiubU"]
        if bad:
            raise BundleError(f"bundle {str(self.root)!r}: {rel} ({what}) holds {arrays[bad[0]].dtype} array "
                              f"{bad[0]!r}, not numbers")
        return arrays

    def program(self, rel: str, what: str = "a NumPy form", n_in: int | None = None,
                out_shape: tuple[int | None, ...] | None = None) -> Program:
        """The NumPy program ``rel``; with ``n_in`` it is run once on one row of that width and its output
        must have ``out_shape`` (None: any size), else a BundleError naming the part."""
        key = f"program:{rel}"
        if key not in self._cache:
            from invphys.inverter.numeric import PROGRAM_KEY

            arrays = self._npz(rel, what)
            try:
                ops = json.loads(str(arrays.pop(PROGRAM_KEY)))
                prog = Program(ops, arrays)
            except (KeyError, ValueError, TypeError, AttributeError) as exc:
                raise BundleError(f"bundle {str(self.root)!r}: {rel} ({what}) is not a NumPy program "
                                  f"({type(exc).__name__})") from None
            if n_in is not None:
                self._fits(prog, rel, what, n_in, out_shape)
            self._cache[key] = prog
        return self._cache[key]

    def _fits(self, prog: Program, rel: str, what: str, n_in: int, out_shape: tuple[int | None, ...] | None) -> None:
        try:
            out = np.asarray(prog(np.full((1, n_in), 0.5)))
        except Exception as exc:  # a program whose arrays do not chain (wrong shapes, missing names, bad ops)
            reason = next((ln.strip() for ln in str(exc).splitlines() if ln.strip()), type(exc).__name__)
            raise BundleError(f"bundle {str(self.root)!r}: {rel} ({what}) does not fit the bundle: it cannot "
                              f"map {n_in} inputs ({reason})") from None
        if out_shape is not None and (out.ndim != len(out_shape) or any(
                want is not None and got != want for got, want in zip(out.shape, out_shape, strict=True))):
            want = tuple("K" if w is None else w for w in out_shape)
            raise BundleError(f"bundle {str(self.root)!r}: {rel} ({what}) does not fit the bundle: one row of "
                              f"{n_in} inputs gives shape {out.shape}, the bundle needs {want}")
