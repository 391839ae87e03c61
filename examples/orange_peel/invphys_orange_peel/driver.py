"""The host-side step driver shared by every backend: dt rule, gripper table, recording, failures.

A backend (Taichi, Warp) only owns state and kernels: ``load(materials)``, ``set_frame(dt, nsub,
grip)``, ``advance(n)``, ``frame_stats(lo, hi)``, ``read()``. Everything that decides *what* is
simulated lives here so that backends agree bit-for-bit on it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from invphys_orange_peel.failure import energy_bound, frame_failure, substep_failure
from invphys_orange_peel.material import Materials
from invphys_orange_peel.scene import Scene


@dataclass(frozen=True)
class StepSettings:
    """Numerical settings of a run (identical for every run of a batch)."""

    cfl: float = 0.4
    velocity_cfl: float = 0.3
    min_substeps_per_frame: int = 4
    max_substeps_per_frame: int = 2000
    gravity: float = 0.0            # m/s^2 along +y (negative pulls down)
    apic_blend: float = 0.0         # 0 = PIC momentum transfer, 1 = APIC
    l0_cells: float = 0.5           # phase-field length scale l0 in cells
    boundary_cells: int = 3
    damage_on: bool = True
    gripper_on: bool = True
    deterministic: bool = True
    energy_factor: float = 4.0


@dataclass
class RunRecord:
    """What the driver returns for one run of a batch."""

    positions: list[np.ndarray] = field(default_factory=list)
    damage: list[np.ndarray] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    substeps: int = 0
    failure: str | None = None
    max_speed: list[float] = field(default_factory=list)
    kinetic_energy: list[float] = field(default_factory=list)


def frame_plan(frame: int, fps: float, dt_bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nsub, dt) per run for one frame: nsub = ceil(frame_dt / dt_bound), dt = frame_dt / nsub."""
    frame_dt = 1.0 / fps
    nsub = np.ceil(frame_dt / dt_bound - 1e-9).astype(np.int64)
    nsub = np.maximum(nsub, 1)
    return nsub, frame_dt / nsub


def gripper_table(scene: Scene, frame: int, fps: float, nsub: np.ndarray, dt: np.ndarray,
                  active: np.ndarray) -> np.ndarray:
    """(B, K, 6): for substep k of run b, gripper displacement since t=0 at its end and its velocity."""
    B = nsub.shape[0]
    K = int(max(1, nsub[active].max() if active.any() else 1))
    k = np.arange(1, K + 1)
    t0 = frame / fps
    t_end = t0 + k[None, :] * dt[:, None]                      # (B, K)
    t_start = t_end - dt[:, None]
    p0 = scene.gripper_position(0.0)
    pe = scene.gripper_position(t_end)
    ps = scene.gripper_position(t_start)
    table = np.zeros((B, K, 6))
    table[..., :3] = pe - p0
    table[..., 3:] = (pe - ps) / dt[:, None, None]
    return table


def run_batch(backend, scene: Scene, materials: Materials, frames: int, fps: float, record_every: int,
              settings: StepSettings) -> tuple[list[RunRecord], float]:
    """Simulate every run of a loaded batch; returns per-run records and the wall time (s)."""
    B = materials.batch
    start = time.perf_counter()
    backend.load(materials)
    records = [RunRecord() for _ in range(B)]
    dx = scene.dx
    lo, hi = 1.5 * dx, scene.domain - 1.5 * dx
    dt_el = materials.elastic_dt(dx, settings.cfl)
    dt_cap = 1.0 / fps / settings.min_substeps_per_frame
    ts = np.linspace(0.0, frames / fps, 20 * frames + 1)
    path = scene.gripper_position(ts)
    grip_speed = float(np.max(np.linalg.norm(np.diff(path, axis=0), axis=1) / np.diff(ts))) \
        if settings.gripper_on else 0.0
    total_mass = materials.rho * scene.volume * scene.n_particles
    bounds = energy_bound(total_mass, materials.wave_speed, grip_speed, settings.energy_factor)
    alive = np.ones(B, bool)

    def record(frame: int) -> None:
        x, d = backend.read()
        for b in np.flatnonzero(alive):
            records[b].positions.append(x[b].copy())
            records[b].damage.append(d[b].copy())
            records[b].frames.append(frame)

    stats = backend.frame_stats(lo, hi)
    record(0)
    for frame in range(frames):
        vmax = stats[:, 0]
        with np.errstate(divide="ignore"):
            dt_v = np.where(vmax > 0, settings.velocity_cfl * dx / np.maximum(vmax, 1e-30), np.inf)
        nsub, dt = frame_plan(frame, fps, np.minimum(np.minimum(dt_cap, dt_el), dt_v))
        for b in np.flatnonzero(alive):
            reason = substep_failure(int(nsub[b]), settings.max_substeps_per_frame, frame, float(vmax[b]))
            if reason:
                records[b].failure, alive[b] = reason, False
        nsub = np.where(alive, nsub, 0)
        if not alive.any():
            break
        if settings.gripper_on:
            grip = gripper_table(scene, frame, fps, nsub, dt, alive)
        else:
            grip = np.zeros((B, 1, 6))
        backend.set_frame(dt, nsub, grip)
        backend.advance(int(nsub.max()))
        stats = backend.frame_stats(lo, hi)
        for b in np.flatnonzero(alive):
            records[b].substeps += int(nsub[b])
            records[b].max_speed.append(float(stats[b, 0]))
            records[b].kinetic_energy.append(float(stats[b, 1]))
            reason = frame_failure(stats[b], float(bounds[b]), frame + 1)
            if reason:
                records[b].failure, alive[b] = reason, False
        if (frame + 1) % record_every == 0 or frame + 1 == frames:
            record(frame + 1)
    backend.sync()
    return records, time.perf_counter() - start


def estimated_substeps(materials: Materials, scene: Scene, frames: int, fps: float,
                       settings: StepSettings) -> np.ndarray:
    """Substeps per run if only the elastic CFL and the dt cap bind (used to group similar runs)."""
    dt = np.minimum(materials.elastic_dt(scene.dx, settings.cfl), 1.0 / fps / settings.min_substeps_per_frame)
    return frames * np.ceil(1.0 / fps / dt - 1e-9)


__all__ = ["RunRecord", "StepSettings", "estimated_substeps", "frame_plan", "gripper_table", "run_batch"]
