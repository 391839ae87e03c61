"""The cheese-cutting scene on the AnisoMPM engine, and the map from parameters to per-run materials.

Geometry (metres, y up): a block of ``BLOCK = (0.06, 0.04, 0.02)`` (length x, height y, depth z) rests on
a sticky board (the plane ``y = 3 dx``), centred in the domain. A wire (a cylinder along z, longer than
the block is deep plus its slide) starts ``GAP`` above the block, centred over it, and moves down at the
preset's speed, sliding along its own axis at ``slice_ratio`` times that speed (press and slice), until
its bottom is ``STOP_FRACTION * height`` above the board, then rests. Gravity is
-9.81 m/s^2; the block settles under its own weight before frame 0 (damage frozen, wire at rest, grid
velocities damped so that it comes to rest).
"""

from __future__ import annotations

import numpy as np
from invphys_anisompm import (
    Box,
    Cylinder,
    EngineOptions,
    HalfSpace,
    MaterialSpec,
    Model,
    Scene,
    SceneBuilder,
    linear_cut,
)

from invphys_cheese_cut.parameters import PARAMETER_NAMES
from invphys_cheese_cut.presets import Preset

BLOCK = (0.06, 0.04, 0.02)
GAP = 0.002
WIRE_HALF_LENGTH = 0.06  # m: longer than the block is deep plus the wire's slide along its axis
STOP_FRACTION = 0.15
EASE = 0.01          # s: the wire's speed ramps over this long at start and stop
GRAVITY = -9.81
SETTLE_DAMPING = 200.0  # 1/s: the block comes to rest under its weight within the settling time
DENSITY_UNIT = 1000.0


def block_box(preset: Preset) -> Box:
    floor = 3 * preset.dx
    c = preset.grid * preset.dx / 2
    lx, ly, lz = BLOCK
    return Box((c - lx / 2, floor, c - lz / 2), (c + lx / 2, floor + ly, c + lz / 2))


def wire_travel(preset: Preset) -> float:
    """Distance (m) the wire moves down."""
    return BLOCK[1] * (1.0 - STOP_FRACTION) + GAP


def cut_seconds(preset: Preset) -> float:
    return wire_travel(preset) / preset.wire_speed


def column_drop(positions: np.ndarray, damage: np.ndarray, scene: Scene) -> np.ndarray:
    """(B,) how far (m) the cheese under the wire has been pushed down: the initial mean height of the
    particles that start within two wire radii of the wire's vertical plane, minus their mean height now."""
    col = scene.info["column"]
    return scene.positions[col, 1].mean() - positions[:, col, 1].mean(axis=1)


def damaged_fraction(positions: np.ndarray, damage: np.ndarray, scene: Scene) -> np.ndarray:
    """(B,) soft fraction of broken particles: mean of sigmoid((d - 0.5) / 0.05)."""
    return np.mean(1.0 / (1.0 + np.exp(-(damage.astype(np.float64) - 0.5) / 0.05)), axis=1)


def build_scene(preset: Preset, **options: object) -> Scene:
    """The engine scene of ``preset`` (deterministic); ``options`` override :class:`EngineOptions` fields."""
    opts = EngineOptions(dx=preset.dx, grid=preset.grid, fps=preset.fps, gravity=GRAVITY,
                         settle_seconds=preset.settle_seconds, settle_damping=SETTLE_DAMPING, **options)  # type: ignore[arg-type]
    box = block_box(preset)
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    cx = 0.5 * (lo[0] + hi[0])
    start_y = hi[1] + GAP + preset.wire_radius
    b = SceneBuilder(opts)
    b.add_body("cheese", box, MaterialSpec())
    b.add_collider("board", HalfSpace((0.0, lo[1], 0.0), (0.0, 1.0, 0.0)), surface="sticky")
    r = preset.slice_ratio
    stretch = float(np.sqrt(1.0 + r * r))  # the path is longer than its drop; the drop keeps wire_speed
    b.add_collider("wire", Cylinder((cx, start_y, 0.5 * (lo[2] + hi[2])), preset.wire_radius, axis=2,
                                    half_length=WIRE_HALF_LENGTH),
                   surface="separate", path=linear_cut((0.0, -1.0, r), wire_travel(preset) * stretch,
                                                       preset.wire_speed * stretch, ease=EASE))
    b.add_reduction("column_drop", column_drop)
    b.add_reduction("damaged_fraction", damaged_fraction)
    scene = b.build()
    scene.info.update(column=np.abs(scene.positions[:, 0] - cx) < 2 * preset.wire_radius, top=float(hi[1]), start_y=float(start_y),
                      wire_radius=preset.wire_radius, centre_x=float(cx), block=np.array([lo, hi]))
    return scene


def model_for(scene: Scene, params: np.ndarray) -> Model:
    """Per-run materials and wire friction for physical parameter rows (B, 7) in PARAMETER_NAMES order."""
    x = np.atleast_2d(np.asarray(params, dtype=np.float64))
    col = dict(zip(PARAMETER_NAMES, x.T, strict=True))
    model = scene.model(len(x))
    model.set_material("cheese", E=col["E"], nu=col["nu"], rho=col["rho"] * DENSITY_UNIT,
                       fracture_stretch=col["fracture_stretch"], eta=col["eta"], residual=col["residual"])
    model.set_friction("wire", col["friction"])
    return model
