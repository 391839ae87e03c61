"""Dataset generation throughput: runs per hour of the ``local`` and ``process`` executors.

Generates the same design with each executor (fresh stores) at an orange-peel preset on this machine
and writes the measurements as JSON::

    .venv/bin/python benchmarks/bench_dataset.py --preset tiny --n 8 --workers 2
    # -> benchmarks/results/dataset_tiny_<hostname>.json

On a GPU machine, the ``local`` executor with feature extraction in worker processes against extraction
in the simulator's thread (``--extract-workers``: one ``local`` variant per value; 0 = in process), same
design, features checked equal::

    python benchmarks/bench_dataset.py --preset paper --arch cuda --n 256 --batch-size 64 \
        --scheduling continuous --executors local --extract-workers 0,4 --out benchmarks/results/dataset_paper_h100.json

``--time-split`` (orange peel, ``local`` executor) records for each variant where its wall went: the stream's
production against its consumer's time between runs (the pipeline: hand-off, stores), the Taichi backend's
synchronising reads, launches and uploads, the hand-off and the store's appends (``time_split`` in the JSON)::

    python benchmarks/bench_dataset.py --preset paper --arch cuda --n 512 --batch-size 64 --scheduling continuous \
        --executors local --extract-workers 4 --warmup 2 --time-split --out dataset_split.json

``runs_per_hour`` is end to end (start-up and kernel compilation included: what a user waits for);
``sim_s_per_run`` is the simulator's own time per run (the store's ``wall_time_s`` column), which excludes
start-up and, with several workers, overlaps.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np


def split_points(backend: str):
    """A :class:`TimeSplit` over the points of an in-process orange-peel dataset where its time goes: the
    stream's production and its consumer (the pipeline: hand-off, stores), the Taichi backend's synchronising
    reads and launches, the hand-off to extraction processes and the store's writes."""
    if str(Path(__file__).parent) not in sys.path:   # loaded by file (tests): its helper module beside it
        sys.path.insert(0, str(Path(__file__).parent))
    from _time_split import TimeSplit
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import DatasetStore
    from invphys.plugins.executors._extract_pool import ExtractionPool

    split = TimeSplit()
    split.wrap_generator(OrangePeelSimulator, "simulate_stream", "stream")
    split.wrap(ExtractionPool, "extract", "hand-off to extraction (caller)")
    split.wrap(DatasetStore, "append", "store append")
    if backend == "taichi":
        from invphys_anisompm.backends.taichi_backend import TaichiBackend

        for method, label in (("frame_end", "frame_end (synchronising read: GPU wait + statistics)"),
                              ("read_slots", "read_slots (particles read)"), ("advance", "advance (launch)"),
                              ("set_frame", "set_frame (uploads)"), ("load_slots", "load_slots (new runs)")):
            split.wrap(TaichiBackend, method, label)
    return split


def _host_stalls():
    """A :class:`HostStalls` (``_host_stalls.py`` beside this file): the main thread sampled, gc pauses timed."""
    if str(Path(__file__).parent) not in sys.path:
        sys.path.insert(0, str(Path(__file__).parent))
    from _host_stalls import HostStalls

    return HostStalls()


def bench(preset: str, n: int, batch_size: int, executors: list[str], workers: int, frames: int | None,
          backend: str, seed: int, arch: str = "cpu", scheduling: str | None = None,
          extract_workers: list[int] | None = None, simulator_type: str = "orange_peel",
          features_type: str | None = None, warmup: int = 0, min_chunk: int | None = None,
          time_split: bool = False, host_profile: bool = False) -> dict:
    import pandas as pd

    from invphys.data.generate import generate_dataset

    sim = {"type": simulator_type, "preset": preset, "arch": arch, "backend": backend,
           "batch_size": batch_size}
    if frames:
        sim["frames"] = frames
    if scheduling:
        sim["scheduling"] = scheduling
    if min_chunk:
        sim["min_chunk"] = min_chunk
    out: dict = {"benchmark": "dataset_generation", "preset": preset, "n": n, "batch_size": batch_size,
                 "frames": frames, "backend": backend, "arch": arch, "scheduling": scheduling, "min_chunk": min_chunk,
                 "command": " ".join(sys.argv), "host": platform.node(), "cpu_count": os.cpu_count(),
                 "python": sys.version.split()[0], "started_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                 "results": {}}
    variants: list[tuple[str, dict]] = []
    for name in executors:
        if name == "local" and extract_workers:
            variants += [(f"local_extract{w}" if w else "local", {"type": "local", "extract_workers": w})
                         for w in extract_workers]
        else:
            variants.append((name, {"type": name} if name == "local" else {"type": name, "workers": workers}))
    feat_block = {"type": features_type} if features_type else None
    if warmup:  # compile the kernels (and fill caches) before any variant is timed
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            generate_dataset(Path(tmp) / "ds", sim, features=feat_block, n=warmup, batch_size=batch_size,
                             seed=seed + 1, progress=False)
            out["warmup"] = {"n": warmup, "wall_s": round(time.perf_counter() - t0, 2)}
    features: dict[str, np.ndarray] = {}
    for name, block in variants:
        with tempfile.TemporaryDirectory() as tmp, (split_points(backend) if time_split else nullcontext()) as split, \
                (_host_stalls() if host_profile else nullcontext()) as stalls:
            t0 = time.perf_counter()
            summary = generate_dataset(Path(tmp) / "ds", sim, features=feat_block, n=n, batch_size=batch_size, seed=seed,
                                       executor=block, progress=False)
            wall = time.perf_counter() - t0
            df = pd.read_parquet(Path(tmp) / "ds")
            from invphys.core.dataset import DatasetStore

            store = DatasetStore(Path(tmp) / "ds")
            features[name] = np.asarray(store.arrays(ok_only=False).y, dtype=np.float64)
            out.setdefault("simulator_identity", store.metadata.get("identity"))
        res = {"executor": block, "wall_s": round(wall, 2), "ok": summary.ok, "failed": summary.failed,
               "runs_per_hour": round(3600 * n / wall, 1),
               "sim_s_per_run": round(float(np.mean(df["wall_time_s"])), 3),
               "substeps_mean": round(float(np.mean(df["substeps"])), 1), "devices": summary.devices}
        if name != variants[0][0] and features[name].shape == features[variants[0][0]].shape:
            a, b = features[name], features[variants[0][0]]
            res["features_equal_to_" + variants[0][0]] = bool(np.array_equal(a, b, equal_nan=True))
            rel = np.abs(a - b) / np.maximum(np.abs(b), 1e-12)  # GPU float atomics: compare the statistics
            res["features_median_rel_diff_to_" + variants[0][0]] = float(np.nanmedian(rel))
            res["features_max_rel_diff_of_means"] = float(np.nanmax(np.abs(np.nanmean(a, 0) - np.nanmean(b, 0))
                                                                      / np.maximum(np.abs(np.nanmean(b, 0)), 1e-12)))
        if split is not None:
            res["time_split"] = split.report(wall)
        if stalls is not None:
            res["host_profile"] = stalls.report()
        out["results"][name] = res
        print(json.dumps(res), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--n", type=int, default=8)
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--executors", default="local,process")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--frames", type=int, default=None, help="override the preset's frame count")
    ap.add_argument("--backend", default="taichi")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--scheduling", default=None, choices=["lockstep", "continuous"])
    ap.add_argument("--min-chunk", type=int, default=None, help="continuous: fewest substeps per host round trip")
    ap.add_argument("--extract-workers", default=None,
                    help="comma list: one local-executor variant per value (feature-extraction processes; 0 = none)")
    ap.add_argument("--simulator-type", default="orange_peel",
                    help="simulator plugin: entry-point name or module:Class (machines without entry points)")
    ap.add_argument("--features-type", default=None, help="extractor plugin (default: the simulator's)")
    ap.add_argument("--warmup", type=int, default=0, help="untimed runs first (kernel compilation)")
    ap.add_argument("--time-split", action="store_true",
                    help="orange peel, local executor: record where each variant's wall goes (time_split)")
    ap.add_argument("--host-profile", action="store_true",
                    help="sample the main thread's stack every 5 ms and time gc pauses (host_profile)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    ew = [int(x) for x in args.extract_workers.split(",")] if args.extract_workers else None
    data = bench(args.preset, args.n, args.batch_size, args.executors.split(","), args.workers, args.frames,
                 args.backend, args.seed, args.arch, args.scheduling, ew, args.simulator_type, args.features_type,
                 args.warmup, args.min_chunk, args.time_split, args.host_profile)
    path = args.out or Path(__file__).parent / "results" / f"dataset_{args.preset}_{platform.node()}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
