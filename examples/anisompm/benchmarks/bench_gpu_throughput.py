"""GPU throughput of the AnisoMPM engine: lock-step vs continuous batching, Taichi and Warp, against a
bare elastic MLS-MPM of the same particle count, in one process.

For each (scene, backend, scheduling) it simulates ``--runs`` random parameter vectors of the cheese-cut
simulator (``full`` preset, and a ``peel``-sized variant at the orange peel paper preset's particle
count) ``--batch`` at a time, after a warm-up that compiles every kernel, and records wall time per run,
the ratio to the paper's 156 s per run, useful particle-substeps per second and the slot efficiency
(useful slot-substeps / launched ones). Results are written to ``--out`` after every measurement, so a
run cut short still leaves its numbers.

    python examples/anisompm/benchmarks/bench_gpu_throughput.py --arch cuda --runs 256 --batch 64 \\
        --out examples/anisompm/benchmarks/results/gpu_throughput.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

PAPER_S_PER_RUN = 156.0


def bare_mpm_rate(n_particles: int, grid: int, batch: int, steps: int, arch: str) -> dict:
    """Particle-substeps/s of a plain batched elastic MLS-MPM (fixed-corotated, APIC, gravity, walls) in
    Taichi: no damage, no colliders, no grips; ``batch`` boxes of ``n_particles`` on ``grid``^3."""
    import taichi as ti
    from invphys_anisompm.backends.taichi_backend import ensure_taichi

    ensure_taichi(arch)
    vec3, mat3 = ti.math.vec3, ti.math.mat3
    dx = 1.0 / grid
    side = round(n_particles ** (1 / 3))
    n = side ** 3
    x = ti.Vector.field(3, ti.f32, (batch, n))
    v = ti.Vector.field(3, ti.f32, (batch, n))
    C = ti.Matrix.field(3, 3, ti.f32, (batch, n))
    F = ti.Matrix.field(3, 3, ti.f32, (batch, n))
    gv = ti.Vector.field(3, ti.f32, (batch, grid, grid, grid))
    gm = ti.field(ti.f32, (batch, grid, grid, grid))
    mu, lam, rho, vol = 1e4, 1e4, 1000.0, (0.5 * dx) ** 3
    dt = 1e-4

    @ti.kernel
    def init():
        for b, p in x:
            i, j, k = p // (side * side), (p // side) % side, p % side
            x[b, p] = vec3(0.3, 0.2, 0.3) + vec3(i, j, k) * 0.5 * dx
            v[b, p] = vec3(0.0)
            C[b, p] = mat3(0.0)
            F[b, p] = ti.Matrix.identity(ti.f32, 3)

    @ti.kernel
    def substep():
        for b, i, j, k in gm:
            gv[b, i, j, k] = vec3(0.0)
            gm[b, i, j, k] = 0.0
        for b, p in x:
            Xp = x[b, p] / dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            U, sig, V = ti.svd(F[b, p])
            J = sig[0, 0] * sig[1, 1] * sig[2, 2]
            R = U @ V.transpose()
            P = 2 * mu * (F[b, p] - R) @ F[b, p].transpose() + ti.Matrix.identity(ti.f32, 3) * lam * J * (J - 1)
            mass = rho * vol
            affine = -dt * vol * 4 / dx / dx * P + mass * C[b, p]
            for a, c, e in ti.static(ti.ndrange(3, 3, 3)):
                off = ti.Vector([a, c, e])
                dpos = (off - fx) * dx
                weight = w[a][0] * w[c][1] * w[e][2]
                gv[b, base + off] += weight * (mass * v[b, p] + affine @ dpos)
                gm[b, base + off] += weight * mass
        for b, i, j, k in gm:
            if gm[b, i, j, k] > 0:
                vel = gv[b, i, j, k] / gm[b, i, j, k] + dt * vec3(0, -9.81, 0)
                if i < 3 or i > grid - 3 or j < 3 or j > grid - 3 or k < 3 or k > grid - 3:
                    vel = vec3(0.0)
                gv[b, i, j, k] = vel
        for b, p in x:
            Xp = x[b, p] / dx
            base = ti.cast(Xp - 0.5, ti.i32)
            fx = Xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
            nv = vec3(0.0)
            nC = mat3(0.0)
            for a, c, e in ti.static(ti.ndrange(3, 3, 3)):
                off = ti.Vector([a, c, e])
                weight = w[a][0] * w[c][1] * w[e][2]
                g = gv[b, base + off]
                nv += weight * g
                nC += 4 / dx * weight * g.outer_product(off - fx)
            v[b, p] = nv
            C[b, p] = nC
            F[b, p] = (ti.Matrix.identity(ti.f32, 3) + dt * nC) @ F[b, p]
            x[b, p] += dt * nv

    init()
    for _ in range(5):
        substep()
    ti.sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        substep()
    ti.sync()
    wall = time.perf_counter() - t0
    return {"particles": n, "grid": grid, "batch": batch, "substeps": steps, "wall_s": wall,
            "particle_substeps_per_s": batch * n * steps / wall}


def measure(engine, model, frames: int, record_every: int, batch: int, scheduling: str, min_chunk: int) -> dict:
    from invphys_anisompm.streaming import SlotCounters

    engine.counters = SlotCounters()
    t0 = time.perf_counter()
    if scheduling == "lockstep":
        recs = engine.run_batched(model, frames, record_every, batch)
    else:
        recs = [r for _, r in engine.stream(model, frames, record_every, batch, min_chunk=min_chunk)]
    engine.backend(batch).sync()
    wall = time.perf_counter() - t0
    c = engine.counters
    n_p = engine.scene.n_particles
    runs = model.n_envs
    return {"runs": runs, "ok": sum(r.ok for r in recs), "wall_s": wall, "s_per_run": wall / runs,
            "x_paper": PAPER_S_PER_RUN / (wall / runs), "slot_efficiency": c.efficiency,
            "useful_substeps": c.useful, "launched_slot_substeps": c.launched, "host_chunks": c.chunks,
            "useful_particle_substeps_per_s": c.useful * n_p / wall,
            "runs_2000_minutes": 2000 * wall / runs / 60}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arch", default="cuda")
    ap.add_argument("--runs", type=int, default=256)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--scenes", default="full,peel", help="cheese presets; 'peel' = full at ~48k particles")
    ap.add_argument("--backends", default="taichi,warp")
    ap.add_argument("--schedulings", default="lockstep,continuous")
    ap.add_argument("--min-chunk", type=int, default=8)
    ap.add_argument("--reference-steps", type=int, default=200)
    ap.add_argument("--deadline-s", type=float, default=1e9, help="skip measurements started after this")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="examples/anisompm/benchmarks/results/gpu_throughput.json")
    a = ap.parse_args(argv)
    t_start = time.perf_counter()

    from invphys_anisompm import Engine
    from invphys_cheese_cut.parameters import parameter_space
    from invphys_cheese_cut.presets import get_preset
    from invphys_cheese_cut.scene import build_scene, model_for
    from invphys_cheese_cut.simulator import CheeseCutSimulator

    from invphys.core.dataset import config_hash

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(a.seed).random((a.runs, space.dim)))
    out = {"command": " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]), "host": platform.node(),
           "python": platform.python_version(), "paper_s_per_run": PAPER_S_PER_RUN, "runs": a.runs,
           "batch": a.batch, "min_chunk": a.min_chunk, "seed": a.seed, "results": [], "reference": []}

    def save() -> None:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=2, default=float))

    for scene_name in a.scenes.split(","):
        base = get_preset("full" if scene_name == "peel" else scene_name)
        preset = dataclasses.replace(base, name="peel", dx=0.002, grid=56) if scene_name == "peel" else base
        scene = build_scene(preset)
        model = model_for(scene, params)
        sim = CheeseCutSimulator(preset=base.name)
        if a.reference_steps and time.perf_counter() - t_start < a.deadline_s:
            ref = bare_mpm_rate(scene.n_particles, preset.grid, a.batch, a.reference_steps, a.arch)
            ref["scene"] = scene_name
            out["reference"].append(ref)
            print(json.dumps(ref, default=float), flush=True)
            save()
        for be in a.backends.split(","):
            if time.perf_counter() - t_start > a.deadline_s:
                break
            engine = Engine(scene, backend=be, arch=a.arch)
            t0 = time.perf_counter()   # warm-up: compile every kernel at this batch size
            warm = model.take(np.arange(min(a.batch, a.runs)))
            engine.run(warm, 1, 1)
            list(engine.stream(warm, 1, 1, a.batch))
            compile_s = time.perf_counter() - t0
            for sched in a.schedulings.split(","):
                if time.perf_counter() - t_start > a.deadline_s:
                    break
                row = measure(engine, model, preset.frames, preset.record_every, a.batch, sched, a.min_chunk)
                row.update(scene=scene_name, particles=scene.n_particles, grid=preset.grid, backend=be,
                           scheduling=sched, device=engine.device, warmup_s=compile_s,
                           simulator=sim.name, simulator_version=sim.version,
                           config_hash=config_hash(sim.config, sim.identity_ignores),
                           preset=dataclasses.asdict(preset))
                out["results"].append(row)
                print(json.dumps({k: row[k] for k in ("scene", "backend", "scheduling", "s_per_run", "x_paper",
                                                      "slot_efficiency", "useful_particle_substeps_per_s")},
                                 default=float), flush=True)
                save()
    out["total_s"] = time.perf_counter() - t_start
    save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
