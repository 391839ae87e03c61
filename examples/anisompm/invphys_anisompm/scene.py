"""The scene API: bodies of particles with materials and fibres, grips, colliders, held regions, reductions.

Build phase (plain Python, no taichi or warp)::

    b = SceneBuilder(EngineOptions(dx=0.004, grid=32, fps=100.0, gravity=-9.81))
    b.add_body("cheese", Box(lo, hi), MaterialSpec(E=1e5, nu=0.35, rho=1100.0))
    b.add_collider("board", HalfSpace(point, (0, 1, 0)), surface="sticky")
    b.add_collider("wire", Cylinder(centre, 0.004, axis=2, half_length=0.05), friction=0.2,
                   path=linear_cut((0, -1, 0), 0.035, 0.25))
    scene = b.build()

Run phase: ``model = scene.model(n_envs=B)`` holds per-run material constants (set them with
``model.set_material``), and :class:`~invphys_anisompm.engine.Engine` advances a model's runs together.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from invphys_anisompm.errors import SceneError
from invphys_anisompm.materials import MaterialSpec
from invphys_anisompm.paths import Path, Static
from invphys_anisompm.regions import Box, Cylinder, HalfSpace, Region, lattice

#: collider surfaces: sticky (moves with the collider), slip (no normal motion, Coulomb friction
#: tangentially), separate (like slip but material may leave the surface)
SURFACES = {"sticky": 0, "slip": 1, "separate": 2}
#: collider shape codes understood by the kernels
SHAPE_HALFSPACE, SHAPE_BOX, SHAPE_CYLINDER = 0, 1, 2


@dataclass(frozen=True)
class EngineOptions:
    """Numerical and physical settings shared by every run of a scene.

    Attributes:
        dx: grid spacing (m). The domain is the cube [0, grid * dx]^3.
        grid: grid cells per side.
        fps: frames per second (features and recordings are per frame; a frame has several substeps).
        gravity: acceleration (m/s^2) along +y (negative pulls down).
        settle_seconds: gravity-only settling before frame 0 (kinematic objects at rest, damage frozen).
        settle_damping: grid velocity damping rate (1/s) while settling (v <- v / (1 + c dt)): the
            bodies come to rest under their weight instead of bouncing (0: none).
        cfl: elastic-wave CFL number: dt <= cfl * dx / c.
        velocity_cfl: particle-velocity CFL number (a per-frame guard).
        min_substeps_per_frame: dt <= frame time / this.
        max_substeps_per_frame: more than this fails the run (a blow-up in disguise).
        eta_dt_factor: dt <= this * min(eta) over damaging bodies: damage resolved in time.
        kinematic_cfl: dt <= this * dx / (peak speed of any collider or grip).
        apic_blend: 0 = PIC momentum transfer (damped), 1 = APIC.
        l0_cells: phase-field length scale l0 in cells.
        boundary_cells: width of the domain walls (material cannot move into them).
        particles_per_cell: lattice points per cell side (2 gives 8 particles per cell).
        damage: evolve damage at all.
        deterministic: serialise CPU scatter so that runs repeat bit-for-bit.
        energy_factor: kinetic-energy blow-up bound factor (see :mod:`invphys_anisompm.failure`).
    """

    dx: float
    grid: int
    fps: float = 24.0
    gravity: float = -9.81
    settle_seconds: float = 0.0
    settle_damping: float = 0.0
    cfl: float = 0.4
    velocity_cfl: float = 0.3
    min_substeps_per_frame: int = 4
    max_substeps_per_frame: int = 4000
    eta_dt_factor: float = 0.1
    kinematic_cfl: float = 0.2
    apic_blend: float = 0.0
    l0_cells: float = 0.5
    boundary_cells: int = 3
    particles_per_cell: int = 2
    damage: bool = True
    deterministic: bool = True
    energy_factor: float = 4.0

    @property
    def domain(self) -> float:
        return self.grid * self.dx

    @property
    def spacing(self) -> float:
        return self.dx / self.particles_per_cell


@dataclass(frozen=True)
class Body:
    name: str
    material: MaterialSpec
    count: int


@dataclass(frozen=True)
class Grip:
    """Particles moved kinematically along ``path``; grid nodes where they hold most mass follow."""

    name: str
    path: Path
    count: int


@dataclass(frozen=True)
class Collider:
    """A rigid kinematic shape acting on the grid every substep (a grid hook)."""

    name: str
    shape: Region
    surface: str
    friction: float
    path: Path

    def encode(self) -> tuple[int, np.ndarray, np.ndarray]:
        """(shape code, a, b) for the kernels: half-space (point, unit normal), box (lo, hi),
        cylinder (centre, (radius, axis, half_length))."""
        s = self.shape
        if isinstance(s, HalfSpace):
            n = np.asarray(s.normal, float)
            return SHAPE_HALFSPACE, np.asarray(s.point, float), n / np.linalg.norm(n)
        if isinstance(s, Box):
            return SHAPE_BOX, np.asarray(s.lo, float), np.asarray(s.hi, float)
        if isinstance(s, Cylinder):
            return SHAPE_CYLINDER, np.asarray(s.centre, float), np.array([s.radius, s.axis, s.half_length], float)
        raise TypeError(f"collider {self.name!r}: shape must be HalfSpace, Box or Cylinder, got {type(s).__name__}")


@dataclass(frozen=True)
class HostReduction:
    """A per-frame statistic computed on the host from the read-back state every ``every`` frames:
    ``fn(positions (B, N, 3), damage (B, N), scene) -> (B,) or (B, K)``."""

    name: str
    fn: Callable[..., np.ndarray]
    every: int = 1


class SceneBuilder:
    """Collects bodies, grips, colliders, held regions and reductions, then :meth:`build` s a :class:`Scene`.

    Bodies are sampled on one lattice of spacing ``dx / particles_per_cell``; a lattice point belongs to
    the *first* body added whose region contains it (add a skin before the flesh it wraps).
    """

    def __init__(self, options: EngineOptions) -> None:
        self.options = options
        self._bodies: list[tuple[str, Region | None, MaterialSpec, Callable[[np.ndarray], np.ndarray] | None]] = []
        self._grips: list[tuple[str, Region, Path, tuple[str, ...] | None]] = []
        self._colliders: list[Collider] = []
        self._held: list[Region] = []
        self._held_masks: list[np.ndarray] = []
        self._reductions: list[HostReduction] = []
        self._names: set[str] = set()
        self._explicit: dict[str, tuple[np.ndarray, np.ndarray | None, float | None]] = {}

    def _name(self, name: str) -> None:
        if not name or name in self._names:
            raise SceneError(f"scene object names must be unique and non-empty, got {name!r} twice")
        self._names.add(name)

    def add_body(self, name: str, region: Region, material: MaterialSpec | None = None,
                 fibres: Callable[[np.ndarray], np.ndarray] | None = None) -> SceneBuilder:
        """A body of particles filling ``region``; ``fibres(points) -> (N, 3)`` unit fibre directions."""
        self._name(name)
        self._bodies.append((name, region, material or MaterialSpec(), fibres))
        return self

    def add_particles(self, name: str, positions: np.ndarray, material: MaterialSpec | None = None,
                      fibres: np.ndarray | None = None, volume: float | None = None) -> SceneBuilder:
        """A body of explicit particles (N, 3) (not taken from the lattice), with optional fibres (N, 3)
        and particle volume (default: the lattice's ``spacing^3``)."""
        self._name(name)
        pts = np.asarray(positions, float).reshape(-1, 3)
        fib = None if fibres is None else np.asarray(fibres, float).reshape(pts.shape)
        self._explicit[name] = (pts, fib, volume)
        self._bodies.append((name, None, material or MaterialSpec(), None))
        return self

    def add_grip(self, name: str, region: Region, path: Path, bodies: tuple[str, ...] | None = None) -> SceneBuilder:
        """Hold the particles of ``bodies`` (default all) inside ``region`` and move them along ``path``."""
        self._name(name)
        self._grips.append((name, region, path, bodies))
        return self

    def add_collider(self, name: str, shape: Region, surface: Literal["sticky", "slip", "separate"] = "separate",
                     friction: float = 0.0, path: Path | None = None) -> SceneBuilder:
        """A rigid kinematic collider (half-space, box or cylinder) moving along ``path``.

        ``friction`` is the Coulomb coefficient of slip/separate surfaces (per run: ``model.set_friction``).
        The material's reaction on it is recorded every frame as the series ``force/<name>`` (N).
        """
        self._name(name)
        if surface not in SURFACES:
            raise SceneError(f"collider {name!r}: surface must be one of {sorted(SURFACES)}, got {surface!r}")
        col = Collider(name, shape, surface, float(friction), path or Static())
        col.encode()
        self._colliders.append(col)
        return self

    def hold(self, region: Region) -> SceneBuilder:
        """Hold the grid nodes inside ``region`` at rest (a clamp, a glued base)."""
        self._held.append(region)
        return self

    def hold_nodes(self, mask: np.ndarray) -> SceneBuilder:
        """Hold the grid nodes where the (grid, grid, grid) boolean ``mask`` is true."""
        g = self.options.grid
        mask = np.asarray(mask, bool)
        if mask.shape != (g, g, g):
            raise SceneError(f"hold_nodes: mask must have shape {(g, g, g)}, got {mask.shape}")
        self._held_masks.append(mask)
        return self

    def add_reduction(self, name: str, fn: Callable[..., np.ndarray], every: int = 1) -> SceneBuilder:
        """A host-side per-frame statistic (see :class:`HostReduction`); recorded as series ``name``."""
        self._name(name)
        self._reductions.append(HostReduction(name, fn, int(every)))
        return self

    def build(self) -> Scene:
        o = self.options
        if not self._bodies:
            raise SceneError("a scene needs at least one body")
        pts_all, body_all, fib_all, vol_all = [], [], [], []
        bodies = []
        # one lattice over the union of the bodies' bounds, so that bodies tile without gaps or overlaps
        regions = [r for _, r, _, _ in self._bodies if r is not None]
        cloud = np.zeros((0, 3))
        if regions:
            lo = np.min([r.bounds()[0] for r in regions], axis=0)
            hi = np.max([r.bounds()[1] for r in regions], axis=0)
            cloud = lattice(Box(tuple(lo), tuple(hi)), o.spacing)
        taken = np.zeros(len(cloud), bool)
        for i, (name, region, mat, fibres) in enumerate(self._bodies):
            vol = o.spacing ** 3
            if region is None:
                pts, fib, v = self._explicit[name]
                vol = v or vol
                fib = np.zeros_like(pts) if fib is None else fib
            else:
                mine = region.contains(cloud) & ~taken
                taken |= mine
                pts = cloud[mine]
                fib = np.zeros_like(pts) if fibres is None else np.asarray(fibres(pts), float).reshape(len(pts), 3)
            if len(pts) == 0:
                raise SceneError(f"body {name!r} has no particles (region empty or covered by earlier bodies)")
            vol_all.append(np.full(len(pts), vol))
            pts_all.append(pts)
            body_all.append(np.full(len(pts), i, np.int32))
            fib_all.append(fib)
            bodies.append(Body(name, mat, len(pts)))
        x = np.concatenate(pts_all)
        body = np.concatenate(body_all)
        fib = np.concatenate(fib_all)
        margin = o.boundary_cells * o.dx
        if x.min() < margin or x.max() > o.domain - margin:
            raise SceneError(f"particles lie outside the domain's interior [{margin:.4g}, {o.domain - margin:.4g}] m "
                             f"(grid {o.grid} x dx {o.dx:.4g})")
        names = [b.name for b in bodies]
        grip = np.full(len(x), -1, np.int32)
        grips = []
        for g, (name, region, path, which) in enumerate(self._grips):
            sel = region.contains(x) & (grip < 0)
            if which is not None:
                unknown = set(which) - set(names)
                if unknown:
                    raise SceneError(f"grip {name!r} names unknown bodies {sorted(unknown)}")
                sel &= np.isin(body, [names.index(n) for n in which])
            if not sel.any():
                raise SceneError(f"grip {name!r} holds no particles")
            grip[sel] = g
            grips.append(Grip(name, path, int(sel.sum())))
        idx = np.arange(o.grid) * o.dx
        nodes = np.stack(np.meshgrid(idx, idx, idx, indexing="ij"), axis=-1).reshape(-1, 3)
        held = np.zeros(len(nodes), bool)
        for region in self._held:
            held |= region.contains(nodes)
        for mask in self._held_masks:
            held |= mask.reshape(-1)
        return Scene(options=o, positions=x, body=body, fibres=fib,
                     volume=np.concatenate(vol_all), grip=grip, bodies=tuple(bodies),
                     grips=tuple(grips), colliders=tuple(self._colliders),
                     held=held.reshape(o.grid, o.grid, o.grid), reductions=tuple(self._reductions))


@dataclass
class Scene:
    """A built scene: the initial particle state and the kinematic objects, shared by every run."""

    options: EngineOptions
    positions: np.ndarray       # (N, 3) float64
    body: np.ndarray            # (N,) int32 body index
    fibres: np.ndarray          # (N, 3) fibre direction (zero: none)
    volume: np.ndarray          # (N,) particle volume (m^3)
    grip: np.ndarray            # (N,) int32 grip index, -1 for free particles
    bodies: tuple[Body, ...]
    grips: tuple[Grip, ...]
    colliders: tuple[Collider, ...]
    held: np.ndarray            # (G, G, G) bool held grid nodes
    reductions: tuple[HostReduction, ...] = ()
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_particles(self) -> int:
        return int(self.positions.shape[0])

    @property
    def body_names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.bodies)

    @property
    def kinematic_names(self) -> tuple[str, ...]:
        """Grips first, then colliders: the order of the kinematic table and of force/work columns."""
        return tuple(g.name for g in self.grips) + tuple(c.name for c in self.colliders)

    @property
    def kinematic_paths(self) -> tuple[Path, ...]:
        return tuple(g.path for g in self.grips) + tuple(c.path for c in self.colliders)

    def body_index(self, name: str) -> int:
        try:
            return self.body_names.index(name)
        except ValueError:
            raise SceneError(f"no body {name!r}; bodies: {', '.join(self.body_names)}") from None

    def body_mask(self, name: str) -> np.ndarray:
        return self.body == self.body_index(name)

    def model(self, n_envs: int):
        """A :class:`~invphys_anisompm.model.Model` of ``n_envs`` runs with the bodies' default materials."""
        from invphys_anisompm.model import Model

        return Model(self, n_envs)

    def summary(self) -> dict[str, Any]:
        return {"particles": self.n_particles, "bodies": {b.name: b.count for b in self.bodies},
                "grips": {g.name: g.count for g in self.grips}, "colliders": [c.name for c in self.colliders],
                "held_nodes": int(self.held.sum()), "dx": self.options.dx, "grid": self.options.grid}


__all__ = ["SURFACES", "Body", "Collider", "EngineOptions", "Grip", "HostReduction", "Scene", "SceneBuilder",
           "SceneError"]
