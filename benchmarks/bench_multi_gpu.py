"""One GPU against several in the same call: the ``ray_actors`` executor (one warm simulator actor per GPU)
running a simulator with continuous batching over ``--runs`` random parameter vectors: the cheese cut
(``--scene cheese_cut``, default) or the orange peel (``--scene orange_peel``, its ``--preset``, e.g. paper).

Both actors are started and warmed up first (kernels compiled at the measured slot count, untimed);
then all rows run on ``--gpus`` actors (one per GPU) and again on the first actor alone (1 GPU), each through
``RayActorsExecutor.run`` with chunks of ``--chunk`` rows pulled by idle actors and features extracted
on the actors, as dataset generation does. Records runs/s, the speed-up, and per actor its GPU, rows,
chunks, busy time and slot efficiency (useful slot-substeps / launched ones), with the simulator's
version and config hash and the command. The cheese scene is its ``full`` preset at ``--dx`` (0.002:
~48k particles, the orange peel paper preset's size, as in ``examples/anisompm/benchmarks/bench_gpu_throughput.py``); the orange peel
runs its preset unchanged (``--dx`` ignored), warmed up by one stream of ``slots + 8`` runs.

    PYTHONPATH=$PWD/benchmarks:... python benchmarks/bench_multi_gpu.py --scene orange_peel --gpus 4 --runs 512 \\
        --slots 32 --chunk 32 --min-chunk 16 --extract-workers 3 --out benchmarks/results/multi_gpu_orange_peel_h200x4.json

On a CPU (a check of the whole path): ``--arch cpu --gpus 0 --preset tiny --dx 0 --runs 8 --slots 2
--chunk 4`` (add ``--scene orange_peel`` for the orange peel).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from invphys_cheese_cut.simulator import CheeseCutSimulator
from pydantic import Field

SIM = "bench_multi_gpu:SizedCheeseCut"
FEATURES = "invphys_cheese_cut.features:CheeseCutFeatures"
ORANGE_SIM = "invphys_orange_peel.simulator:OrangePeelSimulator"
ORANGE_FEATURES = "invphys_orange_peel.features:OrangePeelFeatures"


class SizedCheeseCut(CheeseCutSimulator):
    """The cheese-cut simulator with the preset's grid spacing replaced (``dx``, ``grid``) and the
    engine's ``min_chunk`` exposed: the benchmark's scene through the ordinary plugin path."""

    class Config(CheeseCutSimulator.Config):
        dx: float | None = Field(None, gt=0, description="grid spacing replacing the preset's")
        grid: int | None = Field(None, ge=8, description="grid cells per side replacing the preset's")
        min_chunk: int = Field(8, ge=1, description="fewest substeps per host chunk of the stream")

    @property
    def preset(self):
        base = super().preset
        c = self.config
        return dataclasses.replace(base, name=f"{base.name}@dx{c.dx:g}", dx=c.dx, grid=c.grid) if c.dx else base

    def simulate_stream(self, params: np.ndarray, batch_size: int | None = None):
        from invphys_cheese_cut.scene import model_for

        x = self._check(params)
        for i, rec in self.engine.stream(model_for(self.scene, x), self.preset.frames, self.record_every,
                                         int(batch_size or self.config.batch_size), min_chunk=self.config.min_chunk):
            yield i, self._finished(x[i], rec)


def warm_up(simulator, extractor) -> dict:
    """On an actor: compile every kernel at the configured slot count (the cheese cut: one frame of
    ``2 x batch_size`` runs through the stream, so finished slots are also re-loaded; a simulator without
    a one-frame stream, the orange peel: ``batch_size + 8`` whole runs), then zero the slot counters."""
    import ray
    from invphys_anisompm.streaming import SlotCounters

    t0 = time.perf_counter()
    space = simulator.parameter_space()
    b = getattr(simulator, "batch_size", None) or simulator.config.batch_size
    rng = np.random.default_rng(123)
    if simulator.name == "cheese_cut":
        from invphys_cheese_cut.scene import model_for

        x = space.denormalize(rng.random((2 * b, space.dim)))
        list(simulator.engine.stream(model_for(simulator.scene, x), 1, 1, b, min_chunk=simulator.config.min_chunk))
    else:
        list(simulator.simulate_stream(space.denormalize(rng.random((b + 8, space.dim))), b))
    simulator.engine.counters = SlotCounters()
    ids = [str(g) for g in ray.get_gpu_ids()]
    return {"warmup_s": time.perf_counter() - t0, "device": simulator.engine.device, "gpu_ids": ids,
            "gpu_names": [n for i in ids for n in gpu_names(i)], "particles": int(simulator.scene.n_particles)}


def take_counters(simulator, extractor) -> dict:
    """On an actor: its slot counters since the last call, then zeroed."""
    from invphys_anisompm.streaming import SlotCounters

    c = simulator.engine.counters
    simulator.engine.counters = SlotCounters()
    return {"useful_slot_substeps": int(c.useful), "launched_slot_substeps": int(c.launched),
            "host_chunks": int(c.chunks), "slot_efficiency": c.efficiency}


def gpu_names(index: str | None = None) -> list[str]:
    """``nvidia-smi``'s name and memory of every GPU (or of GPU ``index``); empty without one."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=index,name,memory.total", "--format=csv,noheader",
                              *(["-i", index] if index is not None else [])],
                             capture_output=True, text=True, timeout=30).stdout
        return [line.strip() for line in out.splitlines() if line.strip()]
    except (OSError, subprocess.SubprocessError):
        return []


def measure(ex, spec: dict, features: str, params: np.ndarray, chunk: int, actors: int) -> dict:
    ex.config.actors = actors
    before = {d["pid"]: d for d in ex.actor_info()}
    t0 = time.perf_counter()
    rows = list(ex.run(spec, {"type": features}, params, chunk))
    wall = time.perf_counter() - t0
    counters = ex.apply(take_counters, spec, {"type": features})
    per_actor = []
    for k, (d, c) in enumerate(zip(ex.actor_info(), counters, strict=True)):
        b = before[d["pid"]]
        if k < actors:
            per_actor.append({"gpu_ids": d["gpu_ids"], "cuda_visible_devices": d["cuda_visible_devices"],
                              "rows": d["rows"] - b["rows"], "chunks": d["chunks"] - b["chunks"],
                              "busy_s": d["busy_s"] - b["busy_s"], "builds": d["builds"], **c})
    assert sorted(i for i, _ in rows) == list(range(len(params)))
    return {"actors": actors, "runs": len(params), "ok": sum(r.ok for _, r in rows), "wall_s": wall,
            "runs_per_s": len(params) / wall, "s_per_run": wall / len(params), "per_actor": per_actor}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", choices=("cheese_cut", "orange_peel"), default="cheese_cut")
    ap.add_argument("--arch", default="cuda")
    ap.add_argument("--gpus", type=int, default=2, help="GPUs (actors); 0: CPU actors (a check)")
    ap.add_argument("--runs", type=int, default=256)
    ap.add_argument("--slots", type=int, default=64, help="continuous-batching slots per actor")
    ap.add_argument("--chunk", type=int, default=128, help="rows an idle actor pulls at a time")
    ap.add_argument("--min-chunk", type=int, default=8)
    ap.add_argument("--extract-workers", type=int, default=0,
                    help="processes per actor extracting features while its GPU goes on (0: in the actor)")
    ap.add_argument("--preset", default=None, help="the scene's preset (default: full / paper)")
    ap.add_argument("--dx", type=float, default=0.002, help="cheese: grid spacing (0: the preset's)")
    ap.add_argument("--backend", default="taichi")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="benchmarks/results/multi_gpu.json")
    a = ap.parse_args(argv)
    t_start = time.perf_counter()

    import ray

    from invphys.core.dataset import config_hash
    from invphys.plugins.executors import RayActorsExecutor

    if a.scene == "orange_peel":
        from invphys_orange_peel.simulator import OrangePeelSimulator

        a.preset = a.preset or "paper"
        spec = {"type": ORANGE_SIM, "preset": a.preset, "backend": a.backend, "arch": a.arch,
                "batch_size": a.slots, "scheduling": "continuous", "min_chunk": a.min_chunk}
        ref = OrangePeelSimulator(**{k: v for k, v in spec.items() if k not in ("type", "arch")})
        features, preset_record, hash_note = ORANGE_FEATURES, dataclasses.asdict(ref.preset), "the run identity"
    else:
        from invphys_cheese_cut.presets import get_preset

        a.preset = a.preset or "full"
        base = get_preset(a.preset)
        dx = a.dx or None
        grid = round(base.grid * base.dx / a.dx) if dx else None
        spec = {"type": SIM, "preset": a.preset, "backend": a.backend, "arch": a.arch, "batch_size": a.slots,
                "scheduling": "continuous", "dx": dx, "grid": grid, "min_chunk": a.min_chunk}
        ref = CheeseCutSimulator(preset=a.preset, backend=a.backend, batch_size=a.slots, scheduling="continuous")
        sized = SizedCheeseCut(**{k: v for k, v in spec.items() if k != "type"})
        features, preset_record = FEATURES, dataclasses.asdict(sized.preset)
        hash_note = f"the {a.preset!r} preset's (the run identity); dx/grid replaced as in 'preset'"
    space = ref.parameter_space()
    params = space.denormalize(np.random.default_rng(a.seed).random((a.runs, space.dim)))
    out: dict = {
        "command": " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]]), "host": platform.node(),
        "python": platform.python_version(), "ray": ray.__version__, "gpus": gpu_names(),
        "simulator": ref.name, "simulator_version": ref.version,
        "config_hash": config_hash(ref.config, ref.identity_ignores),
        "config_hash_note": hash_note, "scene": a.scene,
        "preset": preset_record, "backend": a.backend, "arch": a.arch,
        "runs": a.runs, "slots_per_actor": a.slots, "chunk": a.chunk, "min_chunk": a.min_chunk,
        "extract_workers_per_actor": a.extract_workers,
        "seed": a.seed, "features": features, "results": []}

    def save() -> None:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=2, default=float))

    ray.init(num_gpus=a.gpus, include_dashboard=False, log_to_driver=True, configure_logging=False)
    n_actors = max(a.gpus, 2)
    ex = RayActorsExecutor(num_gpus=1 if a.gpus else 0, actors=n_actors, num_cpus_per_actor=1,
                           extract_workers=a.extract_workers, keep_actors=True)
    try:
        t0 = time.perf_counter()
        out["warmup"] = ex.apply(warm_up, spec, {"type": features})
        out["warmup_wall_s"] = time.perf_counter() - t0
        out["actors_info"] = ex.actor_info()
        try:
            import taichi
            out["taichi"] = ".".join(map(str, taichi.__version__))
        except ImportError:
            pass
        print(json.dumps({"warmup": out["warmup"], "wall_s": out["warmup_wall_s"]}), flush=True)
        save()
        for actors in (n_actors, 1):
            row = measure(ex, spec, features, params, a.chunk, actors)
            out["results"].append(row)
            print(json.dumps({k: row[k] for k in ("actors", "ok", "wall_s", "runs_per_s")}), flush=True)
            for d in row["per_actor"]:
                print("   ", json.dumps({k: d[k] for k in ("gpu_ids", "rows", "chunks", "busy_s",
                                                          "slot_efficiency", "host_chunks")}, default=float),
                      flush=True)
            save()
        many, one = out["results"]
        out["speedup"] = many["runs_per_s"] / one["runs_per_s"]
        out["scaling_efficiency"] = out["speedup"] / n_actors
        print(json.dumps({"speedup": out["speedup"]}), flush=True)
    finally:
        ex.close()
        ray.shutdown()
    out["total_s"] = time.perf_counter() - t_start
    out["env"] = {k: os.environ.get(k) for k in ("CUDA_VISIBLE_DEVICES",) if os.environ.get(k) is not None}
    save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
