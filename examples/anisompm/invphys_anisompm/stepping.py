"""Time step planning shared by lock-step (:class:`~invphys_anisompm.engine.Engine`) and streamed runs.

Each run keeps its own time step (:func:`run_dt_bound`) for the whole run unless its particles move too
fast: the velocity guard (:func:`velocity_guard`) then raises a frame's substeps. Colliders and grips move
by :func:`kinematic_table`.
"""

from __future__ import annotations

import math

import numpy as np

from invphys_anisompm.model import Model
from invphys_anisompm.scene import Scene


def dt_bounds(model: Model, frames: int) -> dict[str, np.ndarray]:
    """Each run's dt bounds (s) by name: ``elastic_cfl``, ``min_substeps`` (frame_dt / min_substeps),
    ``eta`` (eta_dt_factor * min eta; inf without damage) and ``kinematic_cfl`` (of the fastest collider or
    grip; inf if none moves)."""
    scene = model.scene
    o = scene.options
    n = model.n_envs
    vk = kinematic_speed(scene, frames)
    return {"elastic_cfl": o.cfl * o.dx / model.wave_speed(),
            "min_substeps": np.full(n, 1.0 / o.fps / o.min_substeps_per_frame),
            "eta": o.eta_dt_factor * model.min_eta() if o.damage else np.full(n, np.inf),
            "kinematic_cfl": np.full(n, o.kinematic_cfl * o.dx / vk if vk > 0 else np.inf)}


def run_dt_bound(model: Model, frames: int) -> np.ndarray:
    """Each run's own dt bound (s): the smallest of its :func:`dt_bounds`."""
    return np.min(np.stack(list(dt_bounds(model, frames).values())), axis=0)


def kinematic_speed(scene: Scene, frames: int) -> float:
    """The peak speed (m/s) of any collider or grip over the run."""
    t_end = frames / scene.options.fps
    return max([p.peak_speed(t_end) for p in scene.kinematic_paths] or [0.0])


def frame_plan(fps: float, dt_bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nsub, dt) per run for one frame: nsub = ceil(frame_dt / dt_bound), dt = frame_dt / nsub."""
    frame_dt = 1.0 / fps
    nsub = np.maximum(np.ceil(frame_dt / dt_bound - 1e-9).astype(np.int64), 1)
    return nsub, frame_dt / nsub


def velocity_guard(nsub_run: np.ndarray, vmax: np.ndarray, dx: float, fps: float, velocity_cfl: float) -> np.ndarray:
    """Substeps per run for the next frame: the run's own count, raised where the last frame's peak
    speed needs more."""
    with np.errstate(divide="ignore"):
        dt_v = np.where(vmax > 0, velocity_cfl * dx / np.maximum(vmax, 1e-30), np.inf)
    need = np.ceil((1.0 / fps) / dt_v - 1e-9)
    need = np.where(np.isfinite(need), need, 0).astype(np.int64)
    return np.maximum(nsub_run, need)


def velocity_guard_one(nsub_run: int, vmax: float, dx: float, fps: float, velocity_cfl: float) -> int:
    """:func:`velocity_guard` for one run, in Python floats (the same IEEE arithmetic, bit for bit; ~10x faster
    than numpy on one-element arrays, and continuous batching calls it at every slot's frame end)."""
    if vmax > 0:
        dt_v = velocity_cfl * dx / max(vmax, 1e-30)
        need = math.ceil((1.0 / fps) / dt_v - 1e-9) if dt_v > 0 and math.isfinite(vmax) else 0
        if need >= 2 ** 63:  # as numpy's int64 cast of such a count: no bound (the energy check fails such a run)
            need = 0
    else:
        need = 0   # no speed, or NaN: no bound from the guard
    return max(int(nsub_run), need)


def kinematic_table(scene: Scene, frame: int, nsub: np.ndarray, dt: np.ndarray, active: np.ndarray) -> np.ndarray:
    """(B, K, n_kinematic, 6): for substep k of run b, each object's displacement since t=0 at the end
    of the substep and its velocity over the substep."""
    paths = scene.kinematic_paths
    B = nsub.shape[0]
    K = int(max(1, nsub[active].max() if active.any() else 1))
    table = np.zeros((B, K, max(len(paths), 1), 6))
    if not paths:
        return table
    k = np.arange(1, K + 1)
    t_end = frame / scene.options.fps + k[None, :] * dt[:, None]
    t_start = t_end - dt[:, None]
    for c, path in enumerate(paths):
        pe, ps = path.displacement(t_end), path.displacement(t_start)
        table[:, :, c, :3] = pe
        table[:, :, c, 3:] = (pe - ps) / dt[:, None, None]
    return table


def estimated_substeps(model: Model, frames: int) -> np.ndarray:
    """Substeps per run if no velocity guard binds (used to batch runs of similar cost)."""
    o = model.scene.options
    nsub, _ = frame_plan(o.fps, run_dt_bound(model, frames))
    return (frames + round(o.settle_seconds * o.fps)) * nsub


__all__ = ["dt_bounds", "estimated_substeps", "frame_plan", "kinematic_speed", "kinematic_table", "run_dt_bound",
           "velocity_guard", "velocity_guard_one"]
