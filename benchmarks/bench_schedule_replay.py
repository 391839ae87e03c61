"""Continuous batching replayed on the host (issue 16): where a dataset's GPU time goes, and what other slot
policies would give. CPU, no physics.

Each random run's substeps per frame are the engine's own plan (:func:`invphys_anisompm.engine.frame_plan` of
its dt bound; exact unless the velocity guard raises a frame), queued costliest first as ``Engine.stream`` does.
The replay walks ``stream_runs``'s chunk rule (``K = max(min remaining, min(min_chunk, max remaining))``;
a slot whose frame ends within a chunk idles to the chunk's end) substep by substep and prices each substep
with a measured curve of GPU time against the number of active runs (``bench_active_runs``, deformed state,
one H100), plus a host cost per chunk. It reports, per policy, the predicted wall and its parts: kernels at
full occupancy, partial occupancy, the host between chunks. ``rollover`` is a policy that does not exist
yet: frames continue on the device across chunk ends (frame statistics and kinematic tables handled there),
and the host steps in only when a run finishes.

The model is checked against measured walls (``--measured``) before its policies are read: a prediction is
a plan for the next change, not a result.

Example::

    python benchmarks/bench_schedule_replay.py --runs 2000 --slots 32 64 \\
        --measured 256:64:16:61.7 512:64:16:114.4 --out benchmarks/results/schedule_replay_paper.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)

CURVE = ROOT / "benchmarks" / "results" / "active_runs_resort_paper_h100.json"
CURVE_FILE = "ar200_r128.json"   # 64 runs after 200 frames, re-sorted every 128 substeps (the default)


def load_curve(path: Path = CURVE, name: str = CURVE_FILE) -> tuple[np.ndarray, np.ndarray]:
    """(active runs, GPU ms per substep), ascending in active runs, from a ``bench_active_runs`` result."""
    rows = json.loads(path.read_text())["files"][name]["rows"]
    pts = sorted((int(r["active_runs"]), float(r["gpu_ms"])) for r in rows)
    return np.array([p[0] for p in pts], float), np.array([p[1] for p in pts])


def replay(nsub: np.ndarray, n_frames: int, slots: int, policy: str, curve: tuple[np.ndarray, np.ndarray],
           host_ms: float) -> dict:
    """Replay runs (``nsub[i]`` substeps in each of ``n_frames`` frames, queued in the given order) through
    ``slots`` slots under ``policy`` (``chunked:<min_chunk>`` or ``rollover:<cap>``); times in seconds."""
    kind, _, arg = policy.partition(":")
    if kind not in ("chunked", "rollover") or not arg.isdigit() or int(arg) < 1:
        raise SystemExit(f"unknown policy {policy!r}: chunked:<min_chunk> or rollover:<cap substeps>")
    limit = int(arg)
    act_pts, ms_pts = curve
    # beyond the curve's largest batch, a batch of `slots` is priced as that batch scaled up
    scale = max(slots / act_pts[-1], 1.0)

    def price_ms(active: np.ndarray) -> np.ndarray:
        return np.interp(active / scale, act_pts, ms_pts) * scale

    full_ms = float(price_ms(np.array([slots]))[0])
    queue = list(range(len(nsub)))[::-1]
    run = np.full(slots, -1)
    rem = np.zeros(slots, np.int64)      # substeps left in the slot's current frame (chunked) or run (rollover)
    frames_left = np.zeros(slots, np.int64)
    gpu_ms = useful = launched = 0.0
    chunks = 0
    while True:
        for b in np.flatnonzero(run < 0)[:len(queue)]:
            i = queue.pop()
            run[b], frames_left[b] = i, n_frames
            rem[b] = nsub[i] if kind == "chunked" else nsub[i] * n_frames
        active = run >= 0
        if not active.any():
            break
        r = rem[active]
        K = int(max(r.min(), min(limit, r.max()))) if kind == "chunked" else int(min(r.min(), limit))
        # active runs at substep s of the chunk: slots whose remaining count exceeds s
        counts = np.bincount(np.minimum(r, K), minlength=K + 1)
        alive = len(r) - np.cumsum(counts)[:K]
        gpu_ms += float(price_ms(alive).sum())
        useful += float(alive.sum())
        launched += slots * K
        chunks += 1
        rem[active] -= np.minimum(r, K)
        ended = active & (rem == 0)
        if kind == "chunked":
            frames_left[ended] -= 1
            more = ended & (frames_left > 0)
            rem[more] = nsub[run[more]]
            run[ended & (frames_left == 0)] = -1
        else:
            run[ended] = -1
    full_s = useful * full_ms / slots / 1e3
    gpu_s, host_s = gpu_ms / 1e3, chunks * host_ms / 1e3
    return {"policy": policy, "slots": slots, "chunks": chunks, "slot_efficiency": useful / launched,
            "predicted_s": gpu_s + host_s, "kernels_at_full_occupancy_s": full_s,
            "partial_occupancy_s": gpu_s - full_s, "host_between_chunks_s": host_s,
            "predicted_s_per_run": (gpu_s + host_s) / len(nsub)}


def plans(preset: str, runs: int, seed: int) -> tuple[np.ndarray, int, dict]:
    """Each random run's substeps per frame (costliest first, as ``Engine.stream`` queues them), the frames
    per run (settling included), and the simulator's identity."""
    from invphys_anisompm.engine import frame_plan, run_dt_bound
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    sim = OrangePeelSimulator(preset=preset, arch="cpu")
    scene, frames = sim.engine_scene, sim.frames
    options = scene.engine.options
    theta = np.random.default_rng(seed).random((runs, sim.parameter_space().dim))
    model = model_for(scene, sim.parameter_space().denormalize(theta))
    nsub, _ = frame_plan(options.fps, run_dt_bound(model, frames))
    n_frames = frames + round(options.settle_seconds * options.fps)
    ident = {"simulator": sim.name, "simulator_version": sim.version, "config_hash": RunIdentity.of(sim).config}
    return np.sort(nsub)[::-1], n_frames, ident


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--runs", type=int, default=2000, help="random parameter vectors (uniform, seed --seed)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--slots", type=int, nargs="+", default=[64])
    ap.add_argument("--policies", nargs="+", default=["chunked:16", "chunked:8", "chunked:4", "chunked:1",
                                                      "rollover:256"])
    ap.add_argument("--host-ms", type=float, default=3.0, help="host time per chunk round trip (GPU idle)")
    ap.add_argument("--measured", nargs="*", default=[], metavar="RUNS:SLOTS:MIN_CHUNK:SECONDS",
                    help="measured walls of bare streams (bench_continuous_gpu, seed --seed) to check the model")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    from _machine import emit  # benchmarks/ is on the path when this runs as a script

    curve = load_curve()
    nsub, n_frames, ident = plans(args.preset, args.runs, args.seed)
    checks = []
    for m in args.measured:
        n, slots, chunk, seconds = m.split(":")
        sub = plans(args.preset, int(n), args.seed)[0]
        pred = replay(sub, n_frames, int(slots), f"chunked:{chunk}", curve, args.host_ms)
        checks.append({"runs": int(n), "slots": int(slots), "min_chunk": int(chunk), "measured_s": float(seconds),
                       "predicted_s": pred["predicted_s"], "ratio": pred["predicted_s"] / float(seconds)})
    rows = [replay(nsub, n_frames, s, p, curve, args.host_ms) for s in args.slots for p in args.policies]
    out = {"benchmark": "schedule_replay", "date": time.strftime("%Y-%m-%d"), "command": "python " + " ".join(sys.argv),
           "device": "none (host replay of the slot schedule, priced with a measured H100 curve)",
           "curve": {"file": f"{CURVE.name}:{CURVE_FILE}", "active_runs": curve[0].tolist(), "gpu_ms": curve[1].tolist()},
           "preset": args.preset, "runs": args.runs, "seed": args.seed, "frames_per_run": n_frames,
           "substeps_mean": float(nsub.mean() * n_frames), "host_ms_per_chunk": args.host_ms, **ident,
           "model_checks": checks, "policies": rows}
    emit(out, args.out)
    return out


if __name__ == "__main__":
    main()
