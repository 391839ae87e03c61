"""Host cost of the orange-peel feature extraction per run (the part of dataset generation the GPU waits for).

    python benchmarks/bench_feature_extraction.py --preset paper --baseline-rev 9277829 \\
        --out benchmarks/results/feature_extraction_paper_cpu.json

The simulator hands each finished run to ``OrangePeelFeatures.extract`` on the host, between launch
batches (``invphys/plugins/executors/_batch.py``), so at the paper preset (51,104 particles, 25 recorded
frames, 3 in the 1 s tail) its time adds to every run's wall time. Trajectories here are synthetic but
full-sized: the preset's built scene, jittered by a growing random displacement (three amplitudes), with
the simulator's per-frame series and a gripped patch; what is timed is the extractor itself.
``--baseline-rev REV`` also times ``features.py`` as committed at git revision REV (loaded from
``git show``) on the same trajectories and checks that both give bit-identical features.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)
FEATURES = "examples/orange_peel/invphys_orange_peel/features.py"


def trajectories(preset_name: str, seed: int) -> list:
    """Three full-size trajectories of the preset's scene (small, medium and large random motion)."""
    from invphys_orange_peel.presets import get_preset
    from invphys_orange_peel.scene import build_scene

    from invphys.core.results import Trajectory

    preset = get_preset(preset_name)
    scene = build_scene(preset)
    x0, n = scene.positions.astype(np.float32), len(scene.positions)
    rng = np.random.default_rng(seed)
    frames = np.arange(0, preset.frames + 1, preset.record_every)
    series = np.arange(preset.frames + 1.0)
    gripped = np.zeros(n, bool)
    gripped[np.argsort(x0[:, 1])[-50:]] = True  # a patch at the top, as the gripper's
    out = []
    for amplitude in (0.002, 0.01, 0.05):
        pos = np.stack([x0 + (k / preset.frames) * amplitude * rng.normal(size=x0.shape).astype(np.float32)
                        for k in frames])
        dmg = np.stack([np.clip(rng.uniform(size=n) * k / preset.frames, 0, 1).astype(np.float32) for k in frames])
        extra = {"radius": 0.15, "dx": 1.0 / preset.grid, "frame_separation": 0.02 + 1e-4 * series,
                 "frame_mean_damage": 1e-3 * series, "frame_work": series / preset.frames,
                 "scene_separation": scene.separation(), "gripped": gripped}
        out.append(Trajectory(positions=pos, damage=dmg, labels=np.asarray(scene.labels, np.int8),
                              frame_indices=frames, fps=preset.fps, extra=extra))
    return out


def module_at(rev: str) -> types.ModuleType:
    """``features.py`` as committed at ``rev``, as a module of its own."""
    src = subprocess.check_output(["git", "show", f"{rev}:{FEATURES}"], cwd=ROOT, text=True)
    mod = types.ModuleType(f"features_at_{rev}")
    exec(compile(src, f"{rev}:{FEATURES}", "exec"), mod.__dict__)
    return mod


def time_extract(extractor, trajs: list, repeat: int) -> tuple[float, list[np.ndarray]]:
    """Median seconds per run over ``repeat`` passes (after one warm-up), and the features of the last pass."""
    extractor.extract(trajs[0])
    passes, feats = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        feats = [extractor.extract(t) for t in trajs]
        passes.append((time.perf_counter() - t0) / len(trajs))
    return float(np.median(passes)), feats


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--baseline-rev", default=None, help="also time features.py at this git revision")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from invphys_orange_peel import SIMULATOR_VERSION
    from invphys_orange_peel.features import OrangePeelFeatures

    from benchmarks._machine import cpu_name

    trajs = trajectories(args.preset, args.seed)
    now, feats = time_extract(OrangePeelFeatures(), trajs, args.repeat)
    out: dict = {
        "benchmark": "bench_feature_extraction", "command": "python " + " ".join([sys.argv[0], *sys.argv[1:]]),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "preset": args.preset,
        "simulator_version": SIMULATOR_VERSION, "particles": int(trajs[0].positions.shape[1]),
        "recorded_frames": int(trajs[0].positions.shape[0]), "runs_per_pass": len(trajs), "repeat": args.repeat,
        "device": {"cpu": cpu_name(), "python": platform.python_version(),
                   "numpy": np.__version__},
        "git": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True).stdout.strip(),
        "extract_s_per_run": round(now, 5),
    }
    if args.baseline_rev:
        base, base_feats = time_extract(module_at(args.baseline_rev).OrangePeelFeatures(), trajs, args.repeat)
        out["baseline"] = {"rev": args.baseline_rev, "extract_s_per_run": round(base, 5),
                           "speedup": round(base / now, 3),
                           "identical_features": all(np.array_equal(a, b) for a, b in zip(base_feats, feats, strict=True))}
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=2))
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
