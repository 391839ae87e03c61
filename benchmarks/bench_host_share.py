"""Where a lock-step batch's wall time goes: GPU substeps against the host's per-frame work (issue 16).

One batch of the orange peel (``Engine.run``: settling, then every frame) with the backend's calls timed:
``advance`` is followed by ``sync``, so its time is the GPU's work on the frame's substeps (launch included);
everything else is the host's per-frame share while the GPU idles: frame statistics and force/work sums
(small device reductions and copies), kinematic tables and uploads (``set_frame``), particle reads for
recorded frames (``read``), failure checks and record keeping in Python (the rest). Kernels are compiled by a
short untimed run first. The figures are per batch frame and per run.

    python benchmarks/bench_host_share.py --preset paper --arch cuda --batch 64 \\
        --out benchmarks/results/host_share_paper_h200.json
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)

from _machine import emit  # noqa: E402

TIMED = ("load", "set_frame", "advance", "frame_stats", "kinematic_sums", "read", "sync")


def instrument(backend, frames: list[dict] | None = None) -> dict[str, list[float]]:
    """Wrap the backend's calls with timers (``advance`` waits for the GPU); returns the running totals.
    With ``frames``, each ``advance`` appends ``{"nsub": the runs' substeps this frame, "steps", "s"}``."""
    totals: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    wait = backend.sync  # the unwrapped one: the GPU wait belongs to advance, not to the sync count
    last_nsub: list[np.ndarray] = [np.zeros(0)]
    for name in TIMED:
        orig = getattr(backend, name)

        def timed(*a, _orig=orig, _name=name, **k):
            if _name == "set_frame":
                last_nsub[0] = np.asarray(a[1] if len(a) > 1 else k["nsub"]).copy()
            t = time.perf_counter()
            out = _orig(*a, **k)
            if _name == "advance":
                totals["advance_issue"][0] += time.perf_counter() - t   # until the launches were issued
                totals["advance_issue"][1] += 1
                wait()
            dt_s = time.perf_counter() - t
            totals[_name][0] += dt_s
            totals[_name][1] += 1
            if _name == "advance" and frames is not None:
                frames.append({"nsub": last_nsub[0], "steps": int(a[0] if a else k["n_steps"]), "s": dt_s})
            return out

        setattr(backend, name, timed)
    return totals


#: bins of the number of runs still active in a lock-step substep
ACTIVE_BINS = ((0, 0), (1, 1), (2, 3), (4, 7), (8, 15), (16, 31), (32, 63), (64, 1 << 30))


def lockstep_profile(frames: list[dict], batch: int) -> dict:
    """Where a lock-step batch's substeps go: every frame launches ``steps`` substeps, and substep ``k`` has
    the runs with ``nsub > k`` active. Returns the lock-step substeps, the runs' own substeps, the efficiency
    (their ratio over the batch size times the lock-step substeps), the mean advance time per lock-step
    substep, how many lock-step substeps had how many runs active (bins), and a least-squares split of the
    frames' advance seconds into a cost per lock-step substep (paid however few runs are active) and a cost
    per run-substep."""
    steps = np.array([f["steps"] for f in frames], float)
    run_substeps = np.array([np.minimum(f["nsub"], f["steps"]).sum() for f in frames], float)
    secs = np.array([f["s"] for f in frames])
    lock, own = int(steps.sum()), int(run_substeps.sum())
    bins = {f"{lo}-{hi}" if hi < 1 << 30 else f">={lo}": 0 for lo, hi in ACTIVE_BINS}
    for f in frames:
        k = np.arange(f["steps"])
        active = (np.asarray(f["nsub"])[None, :] > k[:, None]).sum(axis=1)
        for (lo, hi), key in zip(ACTIVE_BINS, bins, strict=True):
            bins[key] += int(((active >= lo) & (active <= hi)).sum())
    # each frame's advance seconds ~ fixed * its lock-step substeps + per_run * its runs' substeps
    fixed = per_run = float("nan")
    if len(frames) >= 2:
        (fixed, per_run), *_ = np.linalg.lstsq(np.stack([steps, run_substeps], axis=1), secs, rcond=None)
    return {"lockstep_substeps": lock, "run_substeps": own, "efficiency": own / max(lock * batch, 1),
            "fit_ms_per_lockstep_substep": 1e3 * float(fixed), "fit_ms_per_run_substep": 1e3 * float(per_run),
            "advance_ms_per_lockstep_substep": 1e3 * float(secs.sum()) / max(lock, 1),
            "substeps_by_active_runs": bins}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--backend", default="taichi", choices=["taichi", "warp"])
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=None, help="override the preset's frame count")
    ap.add_argument("--kernel-profiler", action="store_true",
                    help="Taichi's kernel profiler on (CUDA events around every launch): the kernels' total GPU "
                         "seconds over the batch, against advance's wall seconds (the events add some overhead)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.kernel_profiler:
        import taichi as ti

        ti.init(arch=ti.cuda if args.arch == "cuda" else ti.cpu, default_fp=ti.f32, random_seed=0,
                offline_cache=True, log_level=ti.WARN, kernel_profiler=True)

    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    settings = {"frames": args.frames} if args.frames else {}
    sim = OrangePeelSimulator(preset=args.preset, arch=args.arch, backend=args.backend, batch_size=args.batch,
                              **settings)
    theta = np.random.default_rng(args.seed).random((args.batch, sim.parameter_space().dim))
    model = model_for(sim.engine_scene, sim.parameter_space().denormalize(theta))
    engine, frames, every = sim.engine, sim.frames, sim.record_every
    t = time.perf_counter()
    engine.run(model, 2, 1)  # compile every kernel at this batch's shapes
    compile_s = time.perf_counter() - t
    frame_log: list[dict] = []
    totals = instrument(engine.backend(args.batch), frame_log)
    if args.kernel_profiler:
        ti.profiler.clear_kernel_profiler_info()
    t = time.perf_counter()
    records = engine.run(model, frames, every)
    wall = time.perf_counter() - t
    calls = {k: {"s": round(v[0], 4), "calls": v[1]} for k, v in totals.items()}
    batch_frames = totals["advance"][1]
    gpu = totals["advance"][0]
    host = wall - gpu
    named = sum(v[0] for k, v in totals.items() if k not in ("advance", "advance_issue"))
    out = {
        "benchmark": "host_share", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_host_share.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "device": engine.device, "backend": args.backend, "simulator": sim.name, "simulator_version": sim.version,
        "preset": args.preset, "config_hash": RunIdentity.of(sim).config, "batch": args.batch, "seed": args.seed,
        "frames": frames, "batch_frames": batch_frames, "runs_ok": sum(r.ok for r in records),
        "substeps_per_run": float(np.mean([r.substeps + r.settle_substeps for r in records])),
        "compile_s": round(compile_s, 2), "wall_s": round(wall, 3), "wall_per_run_s": wall / args.batch,
        "gpu_substeps_s": round(gpu, 3), "host_s": round(host, 3), "host_fraction": host / wall,
        "host_ms_per_batch_frame": 1e3 * host / batch_frames,
        "host_ms_per_run_frame": 1e3 * host / (batch_frames * args.batch),
        "host_python_s": round(host - named, 3), "calls": calls,
        "lockstep": lockstep_profile(frame_log, args.batch),
    }
    if args.kernel_profiler:
        out["kernel_profiler_total_s"] = round(float(ti.profiler.get_kernel_profiler_total_time()), 3)
        ti.profiler.print_kernel_profiler_info("count")   # per kernel: launches, total and mean GPU ms
    emit(out, args.out)
    return out


if __name__ == "__main__":
    main()
