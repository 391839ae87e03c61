"""Particle generation for the orange half and the gripper's arc (pure NumPy, deterministic).

Geometry (all in metres, y up): a cubic domain of ``grid`` cells of size ``dx``; the ground plane at
``y = 3 dx``; the orange half is a hemisphere of radius ``R`` centred on the ground at
``(L/2, 3 dx, L/2)``, cut face down. Particles sit on a regular lattice of spacing ``dx/2``
(8 per cell). Particles within ``skin_cells * dx`` of the dome are skin (label 0), with a fibre
direction along the meridian (tangent, pointing from the rim to the pole); the rest is interior
(label 1). Grid nodes of the flesh's core (up to half the height) are held; a patch of skin at the rim on the +x side is held
by the gripper, which moves along a fixed arc in the x-y plane (up and over the top).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from invphys_orange_peel.presets import ORANGE_RADIUS, Preset

SKIN, INTERIOR = 0, 1
#: boundary padding in cells (walls and ground)
BOUNDARY_CELLS = 3


@dataclass(frozen=True)
class GripperArc:
    """The gripper's path, identical for every run.

    The gripper starts at the dome surface at elevation ``start_deg`` on the +x side and moves along
    a spiral in the x-y plane through the centre's vertical axis: its angle goes from ``start_deg`` to
    ``end_deg`` while its distance from the centre goes from ``R`` to ``radius_factor * R``, with a
    smoothstep time profile between ``t_start`` and ``t_end`` (seconds), at rest before and after.
    """

    start_deg: float = 20.0
    end_deg: float = 150.0
    radius_factor: float = 1.25
    t_start: float = 0.5
    t_end: float = 8.0
    patch_radius: float = 0.3  # in units of R

    def progress(self, t: np.ndarray) -> np.ndarray:
        s = np.clip((np.asarray(t, dtype=np.float64) - self.t_start) / (self.t_end - self.t_start), 0.0, 1.0)
        return s * s * (3.0 - 2.0 * s)

    def position(self, t: np.ndarray | float, centre: np.ndarray, radius: float) -> np.ndarray:
        """Gripper position(s) (..., 3) at time(s) ``t``."""
        s = self.progress(np.asarray(t, dtype=np.float64))
        phi = np.deg2rad(self.start_deg + s * (self.end_deg - self.start_deg))
        rho = radius * (1.0 + (self.radius_factor - 1.0) * s)
        out = np.empty((*np.shape(s), 3))
        out[..., 0] = centre[0] + rho * np.cos(phi)
        out[..., 1] = centre[1] + rho * np.sin(phi)
        out[..., 2] = centre[2]
        return out


@dataclass
class Scene:
    """The initial particle state shared by every run of a preset (per-run arrays come from material)."""

    preset: Preset
    dx: float
    domain: float
    centre: np.ndarray           # (3,) centre of the cut face, on the ground
    radius: float
    skin_thickness: float
    positions: np.ndarray        # (N, 3) float64
    labels: np.ndarray           # (N,) int8, 0 skin / 1 interior
    fibres: np.ndarray           # (N, 3) unit fibre direction (zero for the interior)
    gripped: np.ndarray          # (N,) bool, held by the gripper
    volume: float                # particle volume (dx/2)^3
    arc: GripperArc = field(default_factory=GripperArc)
    hold_height: float = 0.5     # held flesh core: up to this height, in units of R
    hold_margin: float = 1.0     # ... and this many cells inside the skin

    @property
    def n_particles(self) -> int:
        return int(self.positions.shape[0])

    @property
    def ground(self) -> float:
        return float(self.centre[1])

    def gripper_position(self, t: np.ndarray | float) -> np.ndarray:
        return self.arc.position(t, self.centre, self.radius)

    def separation(self) -> float:
        """Distance (m) between the skin's and the interior's centroids as built, before settling."""
        pos = self.positions
        return float(np.linalg.norm(pos[self.labels == SKIN].mean(axis=0) - pos[self.labels == INTERIOR].mean(axis=0)))

    def held_node_mask(self) -> np.ndarray:
        """(G, G, G) bool: grid nodes of the flesh's core whose velocity is held at zero.

        A node is held when it lies inside the interior sphere shrunk by ``hold_margin`` cells and
        no higher than ``hold_height * R`` above the ground (the flesh is held, the skin is free).
        """
        g = self.preset.grid
        idx = np.arange(g) * self.dx
        x, y, z = np.meshgrid(idx, idx, idx, indexing="ij")
        r = np.sqrt((x - self.centre[0]) ** 2 + (y - self.centre[1]) ** 2 + (z - self.centre[2]) ** 2)
        inner = self.radius - self.skin_thickness - self.hold_margin * self.dx
        return (y >= self.ground - 0.01 * self.dx) & (y <= self.ground + self.hold_height * self.radius) \
            & (r <= inner)

    def summary(self) -> dict[str, float | int]:
        return {"particles": self.n_particles, "skin": int((self.labels == SKIN).sum()),
                "interior": int((self.labels == INTERIOR).sum()), "gripped": int(self.gripped.sum()),
                "dx": self.dx, "domain": self.domain, "radius": self.radius,
                "skin_thickness": self.skin_thickness}


def build_scene(preset: Preset, arc: GripperArc | None = None, hold_height: float = 0.5,
                hold_margin: float = 1.0) -> Scene:
    """Generate the particles of ``preset`` (deterministic: same preset, same arrays)."""
    arc = arc or GripperArc()
    radius = ORANGE_RADIUS
    dx = radius / preset.radius_cells
    domain = preset.grid * dx
    ground = BOUNDARY_CELLS * dx
    centre = np.array([domain / 2, ground, domain / 2])
    skin = preset.skin_cells * dx
    h = dx / 2
    n_side = int(np.ceil(2 * radius / h)) + 2
    ax = (np.arange(n_side) + 0.5) * h - n_side * h / 2
    gx, gy, gz = np.meshgrid(ax, (np.arange(n_side) + 0.5) * h, ax, indexing="ij")
    rel = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    r = np.linalg.norm(rel, axis=1)
    keep = r <= radius
    rel, r = rel[keep], r[keep]
    labels = np.where(r >= radius - skin, SKIN, INTERIOR).astype(np.int8)
    # meridional tangent: d/d(elevation) of the unit radial vector, pointing towards the pole
    n = rel / np.maximum(r, 1e-12)[:, None]
    up = np.array([0.0, 1.0, 0.0])
    t = up[None, :] - n * (n @ up)[:, None]
    tn = np.linalg.norm(t, axis=1)
    # at the pole the meridian is undefined: use +x there
    t = np.where(tn[:, None] > 1e-6, t / np.maximum(tn, 1e-12)[:, None], np.array([1.0, 0.0, 0.0]))
    fibres = np.where(labels[:, None] == SKIN, t, 0.0)
    positions = rel + centre
    start = arc.position(0.0, centre, radius)
    gripped = (labels == SKIN) & (np.linalg.norm(positions - start, axis=1) <= arc.patch_radius * radius)
    return Scene(preset=preset, dx=dx, domain=domain, centre=centre, radius=radius, skin_thickness=skin,
                 positions=positions, labels=labels, fibres=fibres, gripped=gripped, volume=h ** 3, arc=arc,
                 hold_height=hold_height, hold_margin=hold_margin)
