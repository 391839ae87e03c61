"""Continuous batching against lock-step on one GPU: the orange peel on the AnisoMPM engine.

Example (one GPU; Taichi CUDA)::

    python examples/anisompm/benchmarks/bench_continuous_gpu.py --preset paper --runs 256 --batch 64 \\
        --cases continuous:16:longest_first continuous:16:given lockstep --budget 420

One process, kernels compiled before timing. ``--cases`` are run in the order given, each only if the
time left in ``--budget`` (s) covers the last case's wall time (the JSON is rewritten after each case):
``lockstep`` (cost-sorted batches, :meth:`Engine.run_batched`) or ``continuous:<min_chunk>:<order>``
(:meth:`Engine.stream`, order ``longest_first`` or ``given``). Per case: seconds per run, slot
efficiency, host chunks, substep launches, useful particle-substeps/s, ratio to the paper's 156 s per
run, failures, and the features' agreement with the first case on the same rows (GPU atomics make runs
differ by round-off). ``--profile`` first times one substep with 64, 32, ... 1 active slots of the batch
(what an idle slot costs) and one chunk's host round trip (uploads, frame statistics and force sums).
Writes ``examples/anisompm/benchmarks/results/continuous_<preset>_<device>[_<tag>].json`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)

PAPER_SECONDS_PER_RUN = 156.0


def profile(sim, params: np.ndarray, batch: int) -> dict:
    """Seconds per substep with n of ``batch`` slots active, and per chunk's host round trip."""
    from invphys_orange_peel.engine_scene import model_for

    eng = sim.engine
    be = eng.backend(batch)
    model = model_for(sim.engine_scene, params[:batch])
    be.load(model.table(), model.friction)
    nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
    dt = np.full(batch, 1.0 / sim.preset.fps / 24)
    K = 20
    kin = np.zeros((batch, K, nk, 6))
    per_substep = {}
    for n in sorted({batch, batch // 2, batch // 4, batch // 8, 4, 1, 0}, reverse=True):
        nsub = np.where(np.arange(batch) < n, K, 0)
        be.set_frame(dt, nsub, kin, damage_on=True)
        be.sync()
        t0 = time.perf_counter()
        be.advance(K)
        be.sync()
        per_substep[str(n)] = (time.perf_counter() - t0) / K
    o = sim.engine_scene.engine.options
    lo, hi = 1.5 * o.dx, o.domain - 1.5 * o.dx
    slots = np.arange(min(4, batch))
    reps = 30
    chunk = {}
    nsub = np.zeros(batch, np.int64)
    kin1 = np.zeros((batch, 16, nk, 6))
    for name in ("separate", "fused", "fused_all_slots"):
        if name == "fused_all_slots":
            slots = np.arange(batch)
        be.sync()
        t0 = time.perf_counter()
        for r in range(reps):
            nsub[:] = r % 3   # changes every chunk, as the real stream's does
            if name == "separate":   # the round trips before frame_end and the upload cache
                getattr(be, "_uploaded", {}).clear()
                be.set_frame(dt, nsub, kin1, damage_on=True)
                be.kinematic_sums(slots)
                be.frame_stats(lo, hi, slots)
            else:
                be.set_frame(dt, nsub, kin1, damage_on=True)
                be.frame_end(lo, hi, slots)
        be.sync()
        chunk[name] = (time.perf_counter() - t0) / reps
    return {"seconds_per_substep_by_active_slots": per_substep, "host_chunk_seconds": chunk,
            "note": "no substeps launched in the chunk timing: uploads, frame statistics kernel, sums, copies back"}


def run_case(sim, params: np.ndarray, batch: int, case: str, ext) -> tuple[dict, np.ndarray | None]:
    from invphys_anisompm.streaming import SlotCounters
    from invphys_orange_peel.engine_scene import model_for

    eng = sim.engine
    eng.counters = SlotCounters()
    model = model_for(sim.engine_scene, params)
    records: dict[int, object] = {}
    finish: list[int] = []
    t0 = time.perf_counter()
    if case == "lockstep":
        eng.run_batched(model, sim.frames, sim.record_every, batch,
                        on_result=lambda i, r: (records.__setitem__(i, r), finish.append(i)))
        mc, order = None, "cost_sorted_batches"
    else:
        _, mc_s, order = case.split(":")
        mc = int(mc_s)
        for i, rec in eng.stream(model, sim.frames, sim.record_every, batch, min_chunk=mc, queue_order=order):
            records[i] = rec
            finish.append(i)
    wall = time.perf_counter() - t0
    c = eng.counters
    n = sim.engine_scene.engine.n_particles
    runs = len(params)
    substeps = np.array([records[i].substeps + records[i].settle_substeps for i in range(runs)])
    feats = None
    if ext is not None:
        feats = np.full((runs, len(ext.feature_names)), np.nan)
        for i in range(runs):
            res = sim.result_from_record(params[i], records[i])
            if res.ok:
                feats[i] = ext.extract(res.trajectory)
    row = {"case": case, "scheduling": "lockstep" if case == "lockstep" else "continuous", "queue_order": order,
           "min_chunk": mc, "batch": batch, "runs": runs, "wall_s": wall, "seconds_per_run": wall / runs,
           "x_paper_156s": PAPER_SECONDS_PER_RUN / (wall / runs),
           "runs_2000_minutes_at_this_rate": 2000 * wall / runs / 60,
           "slot_efficiency": c.efficiency, "host_chunks": c.chunks, "substep_launches": c.launched // batch,
           "useful_slot_substeps": c.useful, "substeps_per_run": {"mean": float(substeps.mean()),
                                                                  "max": int(substeps.max())},
           "useful_particle_substeps_per_s": float(substeps.sum() * n / wall),
           "failed": [records[i].failure for i in range(runs) if records[i].failure],
           "first_finishers": finish[:5]}
    return row, feats


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--arch", default="cuda")
    ap.add_argument("--runs", type=int, default=256)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cases", nargs="+", default=["continuous:16:longest_first", "continuous:16:given", "lockstep"])
    ap.add_argument("--budget", type=float, default=1e9, help="seconds; a case starts only if the last fits")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--no-features", action="store_true", help="skip the feature agreement (host time)")
    ap.add_argument("--p2g", default="auto", choices=["auto", "atomic", "tiled"], help="Taichi scatter (taichi_p2g)")
    ap.add_argument("--resort-every", type=int, default=None,
                   help="substeps between particle re-sorts (taichi_resort_every; default: the simulator's)")
    ap.add_argument("--tag", default="")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    start = time.perf_counter()

    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    sim = OrangePeelSimulator(preset=args.preset, arch=args.arch, batch_size=args.batch, taichi_p2g=args.p2g,
                              taichi_resort_every=args.resort_every)
    space = sim.parameter_space()
    params = space.denormalize(np.random.default_rng(args.seed).uniform(size=(args.runs, space.dim)))
    ext = None if args.no_features else OrangePeelFeatures()
    t0 = time.perf_counter()   # compile every kernel the cases use (run, stream, frame end, gathers)
    warm = model_for(sim.engine_scene, params[:args.batch])
    sim.engine.run(warm, 1, 1)
    list(sim.engine.stream(warm, 1, 1, args.batch))
    warmup = time.perf_counter() - t0
    import taichi as ti

    out = {"benchmark": "bench_continuous_gpu", "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "command": "python examples/anisompm/benchmarks/bench_continuous_gpu.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "device": sim.engine.device, "backend": "taichi", "taichi": ".".join(map(str, ti.__version__)), "simulator": sim.name, "simulator_version": sim.version,
           "p2g": sim.engine.backend(args.batch).p2g, "resort_every": sim.engine.backend(args.batch).resort_every,
           "config_hash": RunIdentity.of(sim).config, "config": sim.config.model_dump(mode="json"),
           "preset": args.preset, "particles": sim.engine_scene.engine.n_particles, "frames": sim.frames,
           "runs": args.runs, "batch": args.batch, "seed": args.seed, "params": "uniform in the normalised space",
           "host": {"cpus": os.cpu_count(), "python": platform.python_version()},
           "warmup_compile_s": warmup, "cases": []}
    dev = "h100" if "H100" in out["device"] else "h200" if "H200" in out["device"] else args.arch
    path = args.out or Path(__file__).resolve().parent / "results" / (
        f"continuous_{args.preset}_{dev}" + (f"_{args.tag}" if args.tag else "") + ".json")
    path.parent.mkdir(parents=True, exist_ok=True)
    if args.profile:
        out["profile"] = profile(sim, params, args.batch)
        print(json.dumps(out["profile"]), flush=True)
        path.write_text(json.dumps(out, indent=2))
    first = None
    last_wall = 0.0
    for case in args.cases:
        left = args.budget - (time.perf_counter() - start)
        if last_wall > left:
            print(f"skip {case}: {left:.0f} s left, last case took {last_wall:.0f} s", flush=True)
            out.setdefault("skipped", []).append(case)
            continue
        row, feats = run_case(sim, params, args.batch, case, ext)
        last_wall = row["wall_s"]
        if feats is None:
            pass
        elif first is None:
            first = feats
        else:   # the same rows through another schedule: feature agreement (GPU round-off only)
            ok = np.isfinite(first).all(axis=1) & np.isfinite(feats).all(axis=1)
            rel = np.abs(feats[ok] - first[ok]) / np.maximum(np.abs(first[ok]), 1e-12)
            row["features_vs_first_case"] = {"rows": int(ok.sum()), "median_rel_diff": float(np.median(rel)),
                                             "max_rel_diff": float(rel.max()) if rel.size else None,
                                             "mean_abs_diff_of_row_means_rel": float(np.max(np.abs(
                                                 feats[ok].mean(0) - first[ok].mean(0))
                                                 / np.maximum(np.abs(first[ok].mean(0)), 1e-12)))}
        out["cases"].append(row)
        print(json.dumps({k: row[k] for k in ("case", "seconds_per_run", "slot_efficiency", "host_chunks",
                                              "x_paper_156s")}), flush=True)
        path.write_text(json.dumps(out, indent=2))
    out["total_s"] = time.perf_counter() - start
    path.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
