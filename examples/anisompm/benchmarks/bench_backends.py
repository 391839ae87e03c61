"""Taichi vs Warp orange-peel backends: feature parity (CPU) and side-by-side speed (GPU).

Both modes simulate the same fixed parameter vectors (``--n`` uniform draws in the unit cube,
``--seed``) on the warm engine of :class:`invphys_orange_peel.simulator.OrangePeelSimulator` (the
``invphys-anisompm`` engine, one backend object per batch size), one batch per backend, and extract the
12 features with :class:`invphys_orange_peel.features.OrangePeelFeatures`.

    # CPU parity at the tiny preset (writes backends_cpu_parity.json)
    python examples/anisompm/benchmarks/bench_backends.py parity --preset tiny --n 16 --batch 4 --out examples/anisompm/benchmarks/results

    # GPU speed at the paper preset, each backend in its own process (writes backends_gpu.json)
    python examples/anisompm/benchmarks/bench_backends.py gpu --preset paper --n 16 --repeats 3 --out examples/anisompm/benchmarks/results

``gpu`` runs Taichi ``--taichi-repeats`` times and Warp ``--repeats`` times (run-to-run spread), while
``--budget-s`` allows; it also times one run alone for 24 frames (Warp with and without CUDA graphs).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from invphys_orange_peel.engine_scene import model_for  # noqa: E402
from invphys_orange_peel.parameters import parameter_space  # noqa: E402
from invphys_orange_peel.presets import get_preset  # noqa: E402
from invphys_orange_peel.scene import build_scene  # noqa: E402
from invphys_orange_peel.simulator import OrangePeelSimulator  # noqa: E402

PAPER_SECONDS_PER_RUN = 156.0


def parameter_set(n: int, seed: int) -> np.ndarray:
    """The fixed benchmark vectors: ``n`` uniform draws in the unit cube, mapped to physical units."""
    unit = np.random.default_rng(seed).uniform(size=(n, parameter_space().dim))
    return parameter_space().denormalize(unit)


def make_backend(name: str, preset: str, batch: int, arch: str, use_graphs: bool | None = None,
                 gpu_deterministic: bool = False) -> OrangePeelSimulator:
    """An orange-peel simulator on backend ``name`` whose engine holds a backend for ``batch`` runs."""
    sim = OrangePeelSimulator(backend=name, preset=preset, arch=arch, batch_size=batch, warp_graphs=use_graphs,
                              gpu_deterministic=gpu_deterministic)
    sim.engine.backend(batch)
    return sim


def max_diff(fa: list, fb: list) -> float:
    """Largest |difference| between two lists of per-run arrays (None entries skipped)."""
    return max((float(np.abs(np.asarray(a) - np.asarray(b)).max()) for a, b in zip(fa, fb, strict=True)
                if a is not None and b is not None), default=0.0)


def deterministic_check(sim, params, frames: int, arch: str) -> dict:
    """Warp on CUDA with and without deterministic atomics: two passes each, same batch, ``frames``."""
    out: dict = {"frames": frames}
    a = simulate(sim, params, frames)
    b = simulate(sim, params, frames)
    out["default"] = {"wall_s": [a["wall_s"], b["wall_s"]],
                      "max_final_position_diff_m": max_diff(a["final_positions"], b["final_positions"])}
    for graphs in (True, False):
        try:
            det = make_backend("warp", sim.config.preset, len(params), arch, use_graphs=graphs, gpu_deterministic=True)
            simulate(det, params, 2, record_every=1)
            a = simulate(det, params, frames)
            b = simulate(det, params, frames)
        except Exception as exc:  # record why, then try without graphs
            out[f"deterministic_graphs_{graphs}_error"] = repr(exc)[:500]
            continue
        out["deterministic"] = {"graphs": graphs, "wall_s": [a["wall_s"], b["wall_s"]],
                                "max_final_position_diff_m": max_diff(a["final_positions"], b["final_positions"]),
                                "features_identical": a["features"] == b["features"]}
        break
    return out


def simulate(sim: OrangePeelSimulator, params: np.ndarray, frames: int, record_every: int | None = None) -> dict:
    """One timed batch on the simulator's warm engine; wall time, substeps, failures, features, throughput."""
    from invphys_orange_peel.features import OrangePeelFeatures

    fe = OrangePeelFeatures()
    t0 = time.perf_counter()
    records = sim.engine.run(model_for(sim.engine_scene, params), frames, record_every or sim.record_every)
    wall = time.perf_counter() - t0
    results = [sim.result_from_record(p, r) for p, r in zip(params, records, strict=True)]
    substeps = [r.substeps for r in records]
    n_particles = sim.scene.n_particles
    return {"wall_s": wall, "wall_per_run_s": wall / len(records), "substeps": substeps,
            "particle_substeps_per_s": n_particles * float(sum(substeps)) / wall,
            "failures": [r.failure for r in results],
            "features": [[float(v) for v in fe.extract(r.trajectory)] if r.ok else None for r in results],
            "final_positions": [r.trajectory.positions[-1] if r.ok else None for r in results]}


def compare(fa: list, fb: list) -> dict:
    """Per-feature Pearson correlation and median relative difference over runs both finished."""
    from invphys_orange_peel.features import FEATURE_NAMES

    both = [i for i, (a, b) in enumerate(zip(fa, fb, strict=True)) if a is not None and b is not None]
    A, B = np.array([fa[i] for i in both]), np.array([fb[i] for i in both])
    out = {"runs_compared": len(both), "features": {}}
    for j, name in enumerate(FEATURE_NAMES):
        a, b = A[:, j], B[:, j]
        scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), 1e-12)
        rel = np.abs(a - b) / scale
        if np.ptp(a) > 0 and np.ptp(b) > 0:
            corr = float(np.corrcoef(a, b)[0, 1])
        else:
            corr = 1.0 if np.allclose(a, b) else float("nan")
        out["features"][name] = {"correlation": corr, "median_rel_diff": float(np.median(rel)),
                                 "max_rel_diff": float(rel.max())}
    corrs = [v["correlation"] for v in out["features"].values()]
    meds = [v["median_rel_diff"] for v in out["features"].values()]
    out["min_correlation"] = float(np.nanmin(corrs))
    out["max_median_rel_diff"] = float(max(meds))
    return out


def machine() -> dict:
    return {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count()}


# -- modes ------------------------------------------------------------------------------------
def cmd_parity(args: argparse.Namespace) -> dict:
    preset = get_preset(args.preset)
    scene = build_scene(preset)
    frames = args.frames or preset.frames
    params = parameter_set(args.n, args.seed)
    result: dict = {"mode": "parity", "preset": preset.name, "particles": scene.n_particles, "frames": frames,
                    "n": args.n, "seed": args.seed, "batch": args.batch, "arch": "cpu",
                    "params": params.tolist(), "machine": machine(), "backends": {}}
    for name in ("taichi", "warp"):
        feats, subs, fails, wall = [], [], [], 0.0
        backends: dict[int, object] = {}
        for s in range(0, args.n, args.batch):
            chunk = params[s:s + args.batch]
            if len(chunk) not in backends:
                backends[len(chunk)] = make_backend(name, preset.name, len(chunk), "cpu")
            r = simulate(backends[len(chunk)], chunk, frames)
            feats += r["features"]
            subs += r["substeps"]
            fails += r["failures"]
            wall += r["wall_s"]
        result["backends"][name] = {"features": feats, "substeps": subs, "failures": fails, "wall_s": wall,
                                    "device": backends[min(backends)].engine.device}
        print(f"{name}: {wall:.1f} s, failures {sum(f is not None for f in fails)}", flush=True)
    result["comparison"] = compare(result["backends"]["taichi"]["features"], result["backends"]["warp"]["features"])
    return result


def cmd_one(args: argparse.Namespace) -> dict:
    """One backend on one device (run in its own process by ``gpu``)."""
    preset = get_preset(args.preset)
    frames = args.frames or preset.frames
    params = parameter_set(args.n, args.seed)
    deadline = time.perf_counter() + args.budget_s
    t0 = time.perf_counter()
    backend = make_backend(args.backend, preset.name, len(params), args.arch)
    init_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    simulate(backend, params, 2, record_every=1)  # compile / capture
    warmup_s = time.perf_counter() - t0
    out = {"backend": args.backend, "device": backend.engine.device, "simulator_version": backend.version, "init_s": init_s, "warmup_s": warmup_s, "passes": []}
    finals = []
    for rep in range(args.repeats):
        r = simulate(backend, params, frames)
        finals.append(r.pop("final_positions"))
        out["passes"].append(r)
        print(f"{args.backend} pass {rep}: {r['wall_s']:.2f} s, {r['particle_substeps_per_s']:.3g} "
              f"particle-substeps/s", flush=True)
        if time.perf_counter() + r["wall_s"] > deadline:
            break
    if len(finals) > 1:  # run-to-run spread of the final particle positions
        diffs = [max(float(np.abs(a - b).max()) for a, b in zip(f0, f1, strict=True)
                     if a is not None and b is not None) for f0, f1 in itertools.pairwise(finals)]
        out["max_final_position_diff_m"] = max(diffs)
    if args.backend == "warp" and args.deterministic_frames and time.perf_counter() < deadline:
        out["gpu_determinism"] = deterministic_check(backend, params, args.deterministic_frames, args.arch)
        print("determinism:", json.dumps(out["gpu_determinism"]), flush=True)
    # one run alone (launch-overhead bound): Warp with and without CUDA graphs, Taichi as is
    variants = {"graphs_on": True, "graphs_off": False} if args.backend == "warp" and args.arch == "cuda" \
        else {"default": None}
    for label, graphs in variants.items():
        b1 = make_backend(args.backend, preset.name, 1, args.arch, use_graphs=graphs)
        simulate(b1, params[:1], 2, record_every=1)
        r = simulate(b1, params[:1], 24)
        out[f"batch1_24_frames_{label}"] = {"wall_s": r["wall_s"], "substeps": r["substeps"][0],
                                            "substeps_per_s": r["substeps"][0] / r["wall_s"]}
    return out


def spread(values: list[float]) -> dict:
    v = np.asarray(values, dtype=np.float64)
    return {"n": len(v), "mean": float(v.mean()), "min": float(v.min()), "max": float(v.max()),
            "rel_spread": float(np.ptp(v) / v.mean()) if len(v) > 1 else 0.0}


def cmd_gpu(args: argparse.Namespace) -> dict:
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    preset = get_preset(args.preset)
    scene = build_scene(preset)
    result: dict = {"mode": "gpu", "preset": preset.name, "particles": scene.n_particles,
                    "frames": args.frames or preset.frames, "n": args.n, "batch": args.n, "seed": args.seed,
                    "params": parameter_set(args.n, args.seed).tolist(), "machine": machine(), "backends": {}}
    start = time.perf_counter()
    for name, repeats in (("taichi", args.taichi_repeats), ("warp", args.repeats)):
        part = out_dir / f"part_{name}.json"
        left = args.budget_s - (time.perf_counter() - start)
        cmd = [sys.executable, __file__, "_one", "--backend", name, "--arch", args.arch, "--preset", preset.name,
               "--n", str(args.n), "--seed", str(args.seed), "--repeats", str(repeats),
               "--budget-s", str(max(left - 30, 1)), "--json", str(part)]
        if args.frames:
            cmd += ["--frames", str(args.frames)]
        if name == "warp" and args.deterministic_frames:
            cmd += ["--deterministic-frames", str(args.deterministic_frames)]
        try:
            code = subprocess.run(cmd, check=False, timeout=max(left, 1)).returncode
        except subprocess.TimeoutExpired:
            code = "timeout"
        if code != 0 or not part.exists():
            result["backends"][name] = {"error": f"exit status {code}"}
            continue
        result["backends"][name] = json.loads(part.read_text())
        part.unlink()
    ok = {k: v for k, v in result["backends"].items() if "passes" in v}
    summary: dict = {}
    for name, v in ok.items():
        walls = [p["wall_per_run_s"] for p in v["passes"]]
        rates = [p["particle_substeps_per_s"] for p in v["passes"]]
        summary[name] = {"wall_per_run_s": spread(walls), "particle_substeps_per_s": spread(rates),
                         "mean_substeps_per_run": float(np.mean(v["passes"][0]["substeps"])),
                         "paper_speedup": PAPER_SECONDS_PER_RUN / float(np.mean(walls))}
    if len(ok) == 2:
        t, w = summary["taichi"], summary["warp"]
        summary["warp_over_taichi_wall"] = w["wall_per_run_s"]["mean"] / t["wall_per_run_s"]["mean"]
        summary["warp_over_taichi_throughput"] = (w["particle_substeps_per_s"]["mean"]
                                                  / t["particle_substeps_per_s"]["mean"])
        summary["feature_parity"] = compare(ok["taichi"]["passes"][0]["features"], ok["warp"]["passes"][0]["features"])
    for name in ok:
        if len(ok[name]["passes"]) > 1:
            summary[f"{name}_run_to_run_features"] = compare(ok[name]["passes"][0]["features"],
                                                             ok[name]["passes"][1]["features"])
    result["summary"] = summary
    return result


def markdown(paths: list[str]) -> str:
    """Markdown tables (as in docs/orange-peel/warp.md) from result JSON files of either mode."""
    lines: list[str] = []
    for path in paths:
        res = json.loads(Path(path).read_text())
        comp = res.get("comparison") or res.get("summary", {}).get("feature_parity")
        if res["mode"] == "gpu":
            s = res["summary"]
            dev = next((v.get("device") for v in res["backends"].values() if "device" in v), "?")
            lines += [f"{res['preset']} preset, {res['particles']:,} particles, {res['frames']} frames, "
                      f"one batch of {res['batch']} runs, {dev}:", "",
                      "| backend | wall time per run (s) | particle-substeps/s | passes | run-to-run spread "
                      "of wall time | speed-up over the paper's 156 s/run |", "|---|---|---|---|---|---|"]
            for name in ("taichi", "warp"):
                if name in s:
                    v = s[name]
                    lines.append(f"| {name} | {v['wall_per_run_s']['mean']:.3f} | "
                                 f"{v['particle_substeps_per_s']['mean']:.3g} | {v['wall_per_run_s']['n']} | "
                                 f"{v['wall_per_run_s']['rel_spread']:.1%} | {v['paper_speedup']:.0f}x |")
            if "warp_over_taichi_wall" in s:
                lines += ["", f"Warp/Taichi: wall time {s['warp_over_taichi_wall']:.3f}, "
                          f"throughput {s['warp_over_taichi_throughput']:.3f}."]
            lines.append("")
        if comp:
            lines += ["| feature | correlation | median rel. diff | max rel. diff |", "|---|---|---|---|"]
            for name, v in comp["features"].items():
                lines.append(f"| {name} | {v['correlation']:.6f} | {v['median_rel_diff']:.1e} | "
                             f"{v['max_rel_diff']:.1e} |")
            lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=["parity", "gpu", "markdown", "_one"])
    ap.add_argument("--preset", default=None)
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--batch", type=int, default=4, help="parity: runs per batch")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=3, help="gpu: Warp passes (run-to-run spread)")
    ap.add_argument("--taichi-repeats", type=int, default=1, help="gpu: Taichi passes")
    ap.add_argument("--deterministic-frames", type=int, default=0,
                    help="gpu: also compare Warp with deterministic atomics over this many frames (0: skip)")
    ap.add_argument("--arch", default="cuda")
    ap.add_argument("--backend", default="warp")
    ap.add_argument("--budget-s", type=float, default=480.0)
    ap.add_argument("--out", default="examples/anisompm/benchmarks/results")
    ap.add_argument("--json", default=None, help="_one: where to write its result")
    ap.add_argument("inputs", nargs="*", help="markdown: result JSON files")
    args = ap.parse_args(argv)
    if args.mode == "markdown":
        print(markdown(args.inputs))
        return 0
    if args.mode == "parity":
        args.preset = args.preset or "tiny"
        res = cmd_parity(args)
        path = Path(args.out) / "backends_cpu_parity.json"
    elif args.mode == "gpu":
        args.preset = args.preset or "paper"
        res = cmd_gpu(args)
        path = Path(args.out) / "backends_gpu.json"
    else:
        args.preset = args.preset or "paper"
        res = cmd_one(args)
        path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=1, default=lambda o: None if o is None else str(o)))
    if "comparison" in res:
        print(json.dumps({k: v for k, v in res["comparison"].items() if k != "features"}))
    if "summary" in res:
        for name in ("taichi", "warp"):
            if name in res["summary"]:
                v = res["summary"][name]
                print(f"{name}: {v['wall_per_run_s']['mean']:.3f} s/run (spread {v['wall_per_run_s']['rel_spread']:.1%}, "
                      f"n={v['wall_per_run_s']['n']}), {v['particle_substeps_per_s']['mean']:.3g} particle-substeps/s, "
                      f"{v['paper_speedup']:.0f}x faster than the paper's 156 s/run")
        for key in ("feature_parity", "taichi_run_to_run_features", "warp_run_to_run_features"):
            if key in res["summary"]:
                c = res["summary"][key]
                print(f"{key}: min corr {c['min_correlation']:.6f}, max median rel diff {c['max_median_rel_diff']:.2e}")
        for key in ("warp_over_taichi_wall", "warp_over_taichi_throughput"):
            if key in res["summary"]:
                print(f"{key}: {res['summary'][key]:.3f}")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
