"""The host-side step driver shared by every backend: dt rule, settling, gripper table, recording, failures.

A backend (Taichi, Warp) only owns state and kernels: ``load(materials)``, ``set_damage_gate(on)``,
``set_frame(dt, nsub, grip)``, ``advance(n)``, ``frame_stats(lo, hi, ref)``, ``read()``. Everything that
decides *what* is simulated lives here so that backends agree bit-for-bit on it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from invphys_orange_peel.failure import (
    STAT_DSUM,
    STAT_ISUM,
    STAT_SSUM,
    STAT_WORK,
    energy_bound,
    frame_failure,
    substep_failure,
)
from invphys_orange_peel.material import Materials
from invphys_orange_peel.scene import Scene


@dataclass(frozen=True)
class StepSettings:
    """Numerical and physical settings of a run (identical for every run of a batch)."""

    cfl: float = 0.4
    velocity_cfl: float = 0.3
    min_substeps_per_frame: int = 4
    max_substeps_per_frame: int = 2000
    eta_dt_factor: float = 0.1      # dt <= eta_dt_factor * min(eta_s, eta_i)
    gravity: float = -0.3           # m/s^2 along +y (negative pulls down); see physics.md
    settle_seconds: float = 0.5     # gravity-only settling before frame 0 (gripper at rest, no damage)
    apic_blend: float = 0.0         # 0 = PIC momentum transfer, 1 = APIC
    l0_cells: float = 0.5           # phase-field length scale l0 in cells
    boundary_cells: int = 3
    damage_on: bool = True
    gripper_on: bool = True
    deterministic: bool = True
    energy_factor: float = 4.0


@dataclass
class RunRecord:
    """What the driver returns for one run of a batch (per-frame series have ``frames + 1`` entries)."""

    positions: list[np.ndarray] = field(default_factory=list)
    damage: list[np.ndarray] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    substeps: int = 0
    settle_substeps: int = 0
    dt: float = 0.0                  # the run's own time step (s) when no velocity guard binds
    guard_frames: int = 0            # frames whose substeps the velocity CFL raised above the run's own
    failure: str | None = None
    max_speed: list[float] = field(default_factory=list)
    kinetic_energy: list[float] = field(default_factory=list)
    separation: list[float] = field(default_factory=list)   # |c_S - c_I| every frame (m)
    mean_damage: list[float] = field(default_factory=list)  # mean d over all particles every frame
    work: list[float] = field(default_factory=list)         # gripper work done so far, every frame (J)


def run_dt_bound(materials: Materials, dx: float, fps: float, settings: StepSettings) -> np.ndarray:
    """Each run's own dt bound (s): min(elastic CFL, frame_dt / min_substeps, eta_dt_factor * min eta)."""
    dt_el = materials.elastic_dt(dx, settings.cfl)
    dt_cap = 1.0 / fps / settings.min_substeps_per_frame
    dt_eta = settings.eta_dt_factor * materials.eta.min(axis=1)
    return np.minimum(np.minimum(dt_el, dt_cap), dt_eta)


def frame_plan(fps: float, dt_bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nsub, dt) per run for one frame: nsub = ceil(frame_dt / dt_bound), dt = frame_dt / nsub."""
    frame_dt = 1.0 / fps
    nsub = np.ceil(frame_dt / dt_bound - 1e-9).astype(np.int64)
    nsub = np.maximum(nsub, 1)
    return nsub, frame_dt / nsub


def velocity_guard(nsub_run: np.ndarray, vmax: np.ndarray, dx: float, fps: float,
                   velocity_cfl: float) -> np.ndarray:
    """Substeps per run for the next frame: the run's own count, raised only where the previous frame's
    peak speed needs more (a safety net: a run's dt stays fixed unless its material moves too fast)."""
    with np.errstate(divide="ignore"):
        dt_v = np.where(vmax > 0, velocity_cfl * dx / np.maximum(vmax, 1e-30), np.inf)
    need = np.ceil((1.0 / fps) / dt_v - 1e-9)
    need = np.where(np.isfinite(need), need, 0).astype(np.int64)
    return np.maximum(nsub_run, need)


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


def frame_series(stats: np.ndarray, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(separation (B,), mean damage (B,)) from the frame statistics (sums relative to the scene centre)."""
    n_skin = max(int((scene.labels == 0).sum()), 1)
    n_int = max(int((scene.labels == 1).sum()), 1)
    cs = stats[:, STAT_SSUM:STAT_SSUM + 3] / n_skin
    ci = stats[:, STAT_ISUM:STAT_ISUM + 3] / n_int
    return np.linalg.norm(cs - ci, axis=1), stats[:, STAT_DSUM] / scene.n_particles


def run_batch(backend, scene: Scene, materials: Materials, frames: int, fps: float, record_every: int,
              settings: StepSettings) -> tuple[list[RunRecord], float]:
    """Simulate every run of a loaded batch; returns per-run records and the wall time (s).

    Order: ``settle_seconds`` of gravity-only settling (gripper at rest, damage frozen, not recorded),
    then frame 0 (recorded: the settled state) and ``frames`` frames of peeling. Every run keeps its
    own dt (:func:`run_dt_bound`) for the whole run unless the velocity guard raises a frame's substeps.
    """
    B = materials.batch
    start = time.perf_counter()
    backend.load(materials)
    records = [RunRecord() for _ in range(B)]
    dx = scene.dx
    lo, hi = 1.5 * dx, scene.domain - 1.5 * dx
    nsub_run, dt_run = frame_plan(fps, run_dt_bound(materials, dx, fps, settings))
    ts = np.linspace(0.0, frames / fps, 20 * frames + 1)
    path = scene.gripper_position(ts)
    grip_speed = float(np.max(np.linalg.norm(np.diff(path, axis=0), axis=1) / np.diff(ts))) \
        if settings.gripper_on else 0.0
    total_mass = materials.rho * scene.volume * scene.n_particles
    bounds = energy_bound(total_mass, materials.wave_speed, grip_speed, settings.energy_factor)
    alive = np.ones(B, bool)
    work = np.zeros(B)
    for b in range(B):
        records[b].dt = float(dt_run[b])

    def step_frame(frame: int, settling: bool, stats: np.ndarray) -> np.ndarray:
        nsub = velocity_guard(nsub_run, stats[:, 0], dx, fps, settings.velocity_cfl)
        dt = (1.0 / fps) / nsub
        for b in np.flatnonzero(alive):
            reason = substep_failure(int(nsub[b]), settings.max_substeps_per_frame, frame, float(stats[b, 0]))
            if reason:
                records[b].failure, alive[b] = reason, False
            elif nsub[b] > nsub_run[b]:
                records[b].guard_frames += 1
        nsub = np.where(alive, nsub, 0)
        if not alive.any():
            return stats
        if settings.gripper_on and not settling:
            grip = gripper_table(scene, frame, fps, nsub, dt, alive)
        else:
            grip = np.zeros((B, int(max(1, nsub.max())), 6))
        backend.set_frame(dt, nsub, grip)
        backend.advance(int(nsub.max()))
        stats = backend.frame_stats(lo, hi, scene.centre)
        for b in np.flatnonzero(alive):
            if settling:
                records[b].settle_substeps += int(nsub[b])
            else:
                records[b].substeps += int(nsub[b])
            reason = frame_failure(stats[b], float(bounds[b]), frame + 1)
            if reason:
                records[b].failure, alive[b] = reason, False
        return stats

    def record(frame: int, stats: np.ndarray, recorded: bool) -> None:
        sep, dmean = frame_series(stats, scene)
        work[:] += stats[:, STAT_WORK]
        x = d = None
        if recorded:
            x, d = backend.read()
        for b in np.flatnonzero(alive):
            r = records[b]
            r.separation.append(float(sep[b]))
            r.mean_damage.append(float(dmean[b]))
            r.work.append(float(work[b]))
            if frame > 0:
                r.max_speed.append(float(stats[b, 0]))
                r.kinetic_energy.append(float(stats[b, 1]))
            if recorded:
                r.positions.append(x[b].copy())
                r.damage.append(d[b].copy())
                r.frames.append(frame)

    stats = backend.frame_stats(lo, hi, scene.centre)
    backend.set_damage_gate(False)
    for s in range(round(settings.settle_seconds * fps)):
        stats = step_frame(-1 - s, True, stats)
        if not alive.any():
            break
    backend.set_damage_gate(settings.damage_on)
    stats[:, STAT_WORK] = 0.0
    record(0, stats, True)
    for frame in range(frames):
        if not alive.any():
            break
        stats = step_frame(frame, False, stats)
        record(frame + 1, stats, (frame + 1) % record_every == 0 or frame + 1 == frames)
    backend.sync()
    return records, time.perf_counter() - start


def estimated_substeps(materials: Materials, scene: Scene, frames: int, fps: float,
                       settings: StepSettings) -> np.ndarray:
    """Substeps per run if no velocity guard binds (used to group runs of similar cost)."""
    nsub, _ = frame_plan(fps, run_dt_bound(materials, scene.dx, fps, settings))
    return (frames + round(settings.settle_seconds * fps)) * nsub


__all__ = ["RunRecord", "StepSettings", "estimated_substeps", "frame_plan", "frame_series", "gripper_table",
           "run_batch", "run_dt_bound", "velocity_guard"]
