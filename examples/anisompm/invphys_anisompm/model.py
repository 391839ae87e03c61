"""Per-run constants of a scene: every run of a batch has its own materials and collider frictions.

``model = scene.model(n_envs=B)`` starts from the bodies' :class:`~invphys_anisompm.materials.MaterialSpec`
defaults; a scene plugin maps its parameters onto it with :meth:`Model.set_material` and
:meth:`Model.set_friction` (arrays of shape (B,) or scalars), optionally for a subset ``envs_idx``.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any, Protocol

import numpy as np

from invphys_anisompm.errors import SceneError
from invphys_anisompm.materials import M_ETA, MaterialSpec, material_columns, wave_speed


class SceneLike(Protocol):
    """What a model reads of its :class:`~invphys_anisompm.scene.Scene` (typed structurally, so that the
    model does not import the scene module, whose ``Scene.model`` builds models)."""

    bodies: tuple[Any, ...]
    colliders: tuple[Any, ...]
    volume: np.ndarray
    body: np.ndarray


class Model:
    """Materials (per run, per body) and frictions (per run, per collider) of ``n_envs`` runs."""

    def __init__(self, scene: SceneLike, n_envs: int) -> None:
        if n_envs < 1:
            raise SceneError(f"n_envs must be >= 1, got {n_envs}")
        self.scene = scene
        self.n_envs = int(n_envs)
        self._values = {b.name: {k: np.full(n_envs, float(v)) for k, v in asdict(b.material).items()}
                        for b in scene.bodies}
        self.friction = np.tile(np.array([c.friction for c in scene.colliders], float), (n_envs, 1)) \
            .reshape(n_envs, len(scene.colliders))

    def set_material(self, body: str, envs_idx: np.ndarray | None = None, **values: np.ndarray | float) -> Model:
        """Set material fields of ``body`` (names of :class:`MaterialSpec`) for all runs or ``envs_idx``."""
        if body not in self._values:
            raise SceneError(f"no body {body!r}; bodies: {', '.join(self._values)}")
        known = MaterialSpec.field_names()
        for key, val in values.items():
            if key not in known:
                raise SceneError(f"unknown material field {key!r}; fields: {', '.join(known)}")
            idx = slice(None) if envs_idx is None else np.asarray(envs_idx)
            self._values[body][key][idx] = np.asarray(val, float)
        return self

    def set_friction(self, collider: str, value: np.ndarray | float, envs_idx: np.ndarray | None = None) -> Model:
        names = [c.name for c in self.scene.colliders]
        if collider not in names:
            raise SceneError(f"no collider {collider!r}; colliders: {', '.join(names) or 'none'}")
        idx = slice(None) if envs_idx is None else np.asarray(envs_idx)
        self.friction[idx, names.index(collider)] = np.asarray(value, float)
        return self

    def material(self, body: str) -> dict[str, np.ndarray]:
        """The per-run values (B,) of every material field of ``body`` (copies)."""
        return {k: v.copy() for k, v in self._values[body].items()}

    def table(self) -> np.ndarray:
        """(B, n_bodies, N_MAT) kernel material table."""
        return np.stack([material_columns(self._values[b.name]) for b in self.scene.bodies], axis=1)

    def take(self, index: np.ndarray) -> Model:
        """A model of the runs ``index`` (in that order)."""
        index = np.asarray(index)
        out = Model(self.scene, len(index))
        out._values = {b: {k: v[index].copy() for k, v in vals.items()} for b, vals in self._values.items()}
        out.friction = self.friction[index].copy()
        return out

    # -- derived per-run quantities -----------------------------------------------------------
    def wave_speed(self) -> np.ndarray:
        """(B,) the largest elastic wave-speed bound over the bodies (m/s)."""
        return wave_speed(self.table()).max(axis=1)

    def min_eta(self) -> np.ndarray:
        """(B,) the smallest damage regularisation (s) over the bodies whose damage evolves (inf if none)."""
        t = self.table()
        dmg = np.stack([self._values[b.name]["damage"] > 0.5 for b in self.scene.bodies], axis=1)
        eta = np.where(dmg, t[..., M_ETA], np.inf)
        return eta.min(axis=1)

    def total_mass(self) -> np.ndarray:
        """(B,) total particle mass (kg)."""
        vol = np.array([self.scene.volume[self.scene.body == i].sum() for i in range(len(self.scene.bodies))])
        rho = np.stack([self._values[b.name]["rho"] for b in self.scene.bodies], axis=1)
        return rho @ vol


__all__ = ["Model", "SceneLike"]
