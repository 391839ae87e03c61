"""Row keys: what makes two simulation runs the same run (:class:`RunIdentity`), and the stable hash of one
run's normalised parameters and identity that the store keys each row by."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

KEY_DECIMALS = 10


@dataclass(frozen=True)
class RunIdentity:
    """What, besides the parameters, makes two simulation runs the same run (part of each row key).

    ``config`` is a hash of the simulator's whole ``Config`` (:func:`config_hash`), so rows made with
    other settings are never reused; fields a simulator lists in its ``identity_ignores`` class
    attribute (e.g. the device) do not count. An empty ``config`` gives the keys of stores made before
    the config was part of the identity.
    """

    simulator: str
    preset: str = ""
    backend: str = ""
    version: str = ""
    config: str = ""

    @classmethod
    def of(cls, simulator: Any) -> RunIdentity:
        """The identity of a :class:`~invphys.core.interfaces.Simulator` instance."""
        cfg = getattr(simulator, "config", None)
        return cls(simulator=str(simulator.name), preset=str(getattr(cfg, "preset", "") or ""),
                   backend=str(getattr(cfg, "backend", "") or ""), version=str(simulator.version),
                   config=config_hash(cfg, getattr(simulator, "identity_ignores", ())))

    def to_dict(self) -> dict[str, str]:
        return {"simulator": self.simulator, "preset": self.preset, "backend": self.backend,
                "version": self.version, "config": self.config}


def extractor_identity(extractor: Any) -> dict[str, Any]:
    """What makes a feature extractor's output the same: its registered name, version, feature names
    and config hash - not how a spec named it (``orange_peel`` or a ``module:Class`` path), so memos of
    features made on one machine are found on another."""
    return {"extractor": str(getattr(extractor, "name", type(extractor).__name__)),
            "version": str(getattr(extractor, "version", "") or ""),
            "features": list(extractor.feature_names),
            "config": config_hash(getattr(extractor, "config", None))}


def config_hash(config: Any, ignore: Sequence[str] = ()) -> str:
    """A stable 16-hex-digit hash of a pydantic config's JSON dump (minus ``ignore``); ``""`` for None."""
    if config is None:
        return ""
    dump = config.model_dump(mode="json") if hasattr(config, "model_dump") else dict(config)
    dump = {k: v for k, v in dump.items() if k not in set(ignore)}
    blob = json.dumps(dump, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def round_theta(theta: np.ndarray) -> np.ndarray:
    """Normalised parameters rounded to the key precision (what the store keeps and keys)."""
    return np.round(np.clip(np.asarray(theta, dtype=np.float64), 0.0, 1.0), KEY_DECIMALS) + 0.0


def row_key(theta_row: Sequence[float] | np.ndarray, identity: RunIdentity) -> str:
    """The stable key of one run: sha256 over fixed-precision text, first 24 hex digits.

    Text (not float bits) makes it identical across processes, machines and NumPy versions.
    """
    values = ",".join(f"{v:.{KEY_DECIMALS}f}" for v in round_theta(np.asarray(theta_row)).ravel())
    text = f"{identity.simulator}|{identity.preset}|{identity.backend}|{identity.version}|{values}"
    if identity.config:
        text += f"|config={identity.config}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def row_keys(theta: np.ndarray, identity: RunIdentity) -> list[str]:
    """Keys of every row of ``theta`` (B, d)."""
    return [row_key(row, identity) for row in np.atleast_2d(theta)]


def keys_fingerprint(keys: Sequence[str]) -> str:
    """A short stable hash of a set of row keys (order does not matter)."""
    return hashlib.sha256("\n".join(sorted(keys)).encode()).hexdigest()[:16]
