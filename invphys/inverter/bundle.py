"""A loaded bundle: its manifest, parameter space, features and (lazily) its networks.

Networks are served by their NumPy inference forms when the bundle has them (no torch import) and
otherwise by their plugins' own ``load`` through the registry. :meth:`Bundle.check_installation`
compares the bundle's simulator and features with the installed plugins.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.params import Parameter, ParameterSpace
from invphys.inverter.manifest import BundleError, python_mismatch, read_manifest
from invphys.inverter.numeric import Program


class FastSurrogate:
    """Surrogate predictions from the bundle (NumPy form, else the plugin): ``predict``, with std."""

    def __init__(self, bundle: Bundle) -> None:
        self._bundle = bundle
        rel = bundle.manifest["components"]["surrogate"].get("inference")
        self._program = Program.load(bundle.root / rel) if rel else None

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
        self._decoder = Program.load(bundle.root / entry["decoder"]) if entry.get("decoder") else None
        self._head = Program.load(bundle.root / entry["head"]) if entry.get("head") else None

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

    def __init__(self, root: str | Path, registry: Any = None, verify: bool = True) -> None:
        self.root = Path(root)
        self.manifest = read_manifest(self.root, verify=verify)
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
        f = m["features"]
        self.feature_names: tuple[str, ...] = tuple(f["names"])
        self.feature_units: tuple[str, ...] = tuple(f.get("units") or [""] * len(self.feature_names))
        self.scales = np.asarray(f["scales"], dtype=np.float64)
        self.kappa = float(f.get("kappa", 3.0))
        self.train_min = np.asarray(f.get("train_min", [-np.inf] * len(self.feature_names)), dtype=np.float64)
        self.train_max = np.asarray(f.get("train_max", [np.inf] * len(self.feature_names)), dtype=np.float64)
        if len(self.scales) != len(self.feature_names):
            raise BundleError(f"{self.root}: {len(self.scales)} feature scales for {len(self.feature_names)} features")
        msg = python_mismatch(m.get("system_info") or {})
        if msg:
            warnings.warn(msg, stacklevel=3)

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

    def check_installation(self, strict: bool = True) -> list[str]:
        """Compare the bundle's simulator version and features with the installed plugins.

        A different simulator version, or an extractor computing other features, raises
        :class:`BundleError` when ``strict`` (else becomes a returned warning). A simulator that is not
        installed is a warning: inversion works, validation and ``--observed`` do not.
        """
        sim = self.manifest["simulator"]
        problems: list[str] = []
        notes: list[str] = []
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
        if block.get("type") and not problems:
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
        cls = self.registry.get(kind, entry["type"])
        return cls.load(self.root / entry["path"])

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
            path = self.root / "data" / f"{split}.npz"
            if not path.is_file():
                raise BundleError(f"bundle {self.root} has no {split} data ({path.name})")
            with np.load(path, allow_pickle=False) as d:
                self._cache[key] = (d["theta"].astype(np.float64), d["y"].astype(np.float64))
        return self._cache[key]

    def program(self, rel: str) -> Program:
        key = f"program:{rel}"
        if key not in self._cache:
            self._cache[key] = Program.load(self.root / rel)
        return self._cache[key]
