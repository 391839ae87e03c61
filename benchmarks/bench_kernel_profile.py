"""Where a substep's GPU time goes: Nsight Compute metrics of the orange peel's Taichi kernels.

Issue 16 asks for a ~3x faster substep. The P2G scatter takes about 70 % of it; whether it is bound by its
float atomics (memory/L2) or by its per-particle arithmetic (SVD, stress, fibre terms) decides the next
lever (block-local accumulation and fewer atomics, or cheaper arithmetic). This script answers that:

    python benchmarks/bench_kernel_profile.py --preset paper --batch 64 [--p2g tiled] --out $OUT/kernel_profile.json

It re-runs itself under ``ncu`` (``--child``): the child builds the warm engine for ``--batch`` random
parameter vectors (seed 0), advances ``--warm`` substeps, then two more; ``ncu`` skips the warm-up's
launches and profiles the next substep's (each Taichi kernel is two CUDA kernels: a short serial task,
then its loop; the committed ``kernel_profile_paper_h200.json`` skipped 4 per substep, so it profiled
substep 11 of the warm-up: same stages, same state class) (sections SpeedOfLight, MemoryWorkloadAnalysis, ComputeWorkloadAnalysis,
LaunchStats, Occupancy, WarpStateStats) and the parent writes every metric per kernel to the JSON, with
the GPU, the simulator's version and config hash and the command. Without ``ncu`` on the PATH it exits 2.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import io
import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

SECTIONS = ["SpeedOfLight", "MemoryWorkloadAnalysis", "ComputeWorkloadAnalysis", "LaunchStats", "Occupancy",
            "WarpStateStats"]
STAGES = "clear_grid|p2g|grid_update|g2p"


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--warm", type=int, default=20, help="substeps advanced before the profiled ones")
    p.add_argument("--dt", type=float, default=1e-4, help="substep (s) of the warm-up and profiled substeps")
    p.add_argument("--arch", default="cuda", help="cpu: a check of the child alone (no ncu)")
    p.add_argument("--p2g", default="atomic", choices=["atomic", "tiled"], help="the Taichi scatter profiled")
    p.add_argument("--g2p", default="unrolled", choices=["unrolled", "loop"], help="the g2p form profiled")
    p.add_argument("--metrics", default="", help="extra ncu metrics, comma-separated (e.g. instruction counts "
                                                 "by kind: smsp__sass_inst_executed_op_shared_atom.sum)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def _child(a: argparse.Namespace) -> None:
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.batch, space.dim)))
    sim = OrangePeelSimulator(backend="taichi", preset=a.preset, arch=a.arch, batch_size=a.batch, taichi_p2g=a.p2g,
                              taichi_g2p=a.g2p)
    backend = sim.engine.backend(a.batch)
    model = model_for(sim.engine_scene, params)
    backend.load(model.table(), model.friction)
    nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
    n = a.warm + 1
    backend.set_frame(np.full(a.batch, a.dt), np.full(a.batch, n), np.zeros((a.batch, n, nk, 6)), damage_on=True)
    backend.advance(a.warm)  # not profiled (--launch-skip)
    backend.sync()
    backend.kernel_times(2)  # the profiled launches: two substeps of the four stages
    ident = RunIdentity.of(sim)
    info = {"particles": int(backend.x.shape[1]), "simulator": ident.simulator,
            "simulator_version": ident.version, "config_hash": ident.config}
    print("CHILD_INFO " + json.dumps(info), flush=True)


def _parse(text: str) -> dict[str, dict[str, dict[str, str]]]:
    """ncu --csv --page details rows -> {kernel: {section: {metric: 'value unit'}}}."""
    rows = list(csv.DictReader(io.StringIO(text[text.index('"ID"'):])))
    out: dict[str, dict[str, dict[str, str]]] = {}
    for r in rows:
        name = r["Kernel Name"].split("(")[0]
        out.setdefault(name, {}).setdefault(r["Section Name"], {})[r["Metric Name"]] = \
            f"{r['Metric Value']} {r['Metric Unit']}".strip()
    return out


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    if a.child:
        _child(a)
        return 0
    ncu = shutil.which("ncu") or next((str(p) for p in Path("/opt/nvidia").glob("nsight-compute/*/ncu")), None)
    if ncu is None:
        print("bench_kernel_profile: ncu (Nsight Compute) is not on the PATH", file=sys.stderr)
        return 2
    # --launch-skip: the warm-up substeps, counted over the kernels the filter matches: 4 stages, each a
    # Taichi kernel of two CUDA kernels (a short serial task, then the loop)
    cmd = [ncu, "--csv", "--page", "details", "--target-processes", "all", "-k", f"regex:{STAGES}",
           "--launch-skip", str(8 * a.warm), "--launch-count", "8", "--clock-control", "none"]
    for s in SECTIONS:
        cmd += ["--section", s]
    if a.metrics:
        cmd += ["--metrics", a.metrics]
    child = [sys.executable, str(Path(__file__).resolve()), "--child", "--preset", a.preset, "--batch",
             str(a.batch), "--warm", str(a.warm), "--dt", str(a.dt), "--p2g", a.p2g, "--g2p", a.g2p]
    proc = subprocess.run(cmd + child, capture_output=True, text=True)
    if a.out:  # ncu's own CSV beside the JSON, whatever happens to the parsing
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.with_suffix(".csv").write_text(proc.stdout)
    if proc.returncode != 0 or '"ID"' not in proc.stdout:
        print(proc.stdout[-3000:], proc.stderr[-3000:], sep="\n", file=sys.stderr)
        return 1
    info = next((json.loads(line[len("CHILD_INFO "):]) for line in proc.stdout.splitlines()
                 if line.startswith("CHILD_INFO ")), {})
    gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                         text=True).stdout.strip()
    kernels = _parse(proc.stdout)
    out = {"benchmark": "bench_kernel_profile", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "device": gpu, "preset": a.preset, "batch": a.batch, "p2g": a.p2g,
           "g2p": a.g2p, "warm_substeps": a.warm, "dt": a.dt,
           "ncu": " ".join(cmd), **info, "kernels": kernels}
    text = json.dumps(out, indent=1) + "\n"
    if a.out:
        a.out.write_text(text)
    for name, secs in kernels.items():
        sol = secs.get("GPU Speed Of Light Throughput", {})
        print(name, {k: sol.get(k) for k in ("Duration", "Compute (SM) Throughput", "Memory Throughput",
                                                "L2 Cache Throughput", "DRAM Throughput")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
