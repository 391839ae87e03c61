"""Reads and uploads between a stream's chunks: Taichi's ``to_numpy``/``from_numpy`` against one direct copy (issue 16).

At a stream's frame end the engine reads the particles (positions and damage, the scene's order) of every slot
at a recorded frame, with the GPU idle until the next launch. ``TaichiBackend.read_slots`` gathers them on the
device, then copies them into new host arrays; this times that read for ``--slots`` runs of a ``--batch``
through each host copy, alternating, after checking they return the same arrays:

- ``to_numpy``: Taichi's, which stages the host array through a device buffer (a copy each way and a kernel);
- ``direct``: ``HostCopy`` (``cuMemcpyDtoH`` on CUDA, ``memmove`` on the CPU) into one new array;
- ``direct_into_reused_arrays``: the same into arrays touched before (the copy alone, no page faults);
- ``fresh_pages_only``: no copy, only new arrays of the read's size written once (their page faults).

Also times ``frame_end`` (the statistics of a frame end: a mask upload, a kernel, one small read) and
``set_frame`` (a chunk's uploads: time steps, substep counts, a 64-substep kinematic table) each way: with
``from_numpy`` (forced) and with ``HostUpload`` (``cuMemcpyHtoD``). The particles read must be
equal bit for bit (``same_arrays``); ``frame_end``'s statistics are float sums whose order GPU atomics vary
between calls, so their largest relative difference is recorded instead.

    python examples/anisompm/benchmarks/bench_host_reads.py --preset paper --batch 64 --slots 60 --out examples/anisompm/benchmarks/results/host_reads_uploads_paper_h100.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import shlex
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm",
          ROOT / "benchmarks"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import emit  # noqa: E402


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--slots", type=int, default=60, help="runs read at once (a paper frame end reads ~60)")
    p.add_argument("--arch", default="cuda", help="cpu: a check of the script (times mean nothing there)")
    p.add_argument("--repeats", type=int, default=10, help="timed reads per copy (alternating)")
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def _timed(fn, forced: str | None, backend) -> float:
    """Seconds for ``fn()`` with the backend's host copies and uploads forced to ``to_numpy``/``from_numpy``
    (``forced``) or direct (``_fallback`` set directly: a forced path is not a fallback worth a warning)."""
    backend.host_copy._fallback = forced
    backend.upload._fallback = forced
    backend.sync()
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.batch, space.dim)))
    sim = OrangePeelSimulator(backend="taichi", preset=a.preset, arch=a.arch, batch_size=a.batch)
    ident = RunIdentity.of(sim)
    backend = sim.engine.backend(a.batch)
    model = model_for(sim.engine_scene, params)
    backend.load(model.table(), model.friction)
    direct_fallback = backend.host_copy.fallback
    if direct_fallback is not None:
        raise SystemExit(f"error: no direct copy here ({direct_fallback})")
    slots = np.arange(min(a.slots, a.batch))
    o = sim.engine_scene.engine.options
    lo, hi = 1.5 * o.dx, o.domain - 1.5 * o.dx

    def read():
        return backend.read_slots(slots)

    def end():
        return backend.frame_end(lo, hi, slots)

    backend.host_copy._fallback = "forced"
    ref, ref_end = read(), end()
    backend.host_copy._fallback = None
    got, got_end = read(), end()
    idx, xo, do = backend._gather_bufs[len(slots)]
    copy = backend.host_copy

    def gather() -> None:
        backend._gather(idx, backend.sid, backend.x, backend.d, xo, do)

    reused = [np.empty_like(ref[0]), np.empty_like(ref[1])]
    for r in reused:
        r[...] = 0   # touched once: no page faults in the timed copies

    def read_reused():
        gather()
        copy._copy_into(reused[0], xo)
        copy._copy_into(reused[1], do)

    def fresh_pages():
        for r in ref:
            np.empty_like(r)[...] = 0

    # the particles read must be equal; frame_end's statistics are float sums whose order GPU atomics vary
    same = all(np.array_equal(r, g) for r, g in zip(ref, got, strict=True))
    end_diff = max(float(np.abs(r - g).max() / max(np.abs(r).max(), 1e-30)) for r, g in zip(ref_end, got_end, strict=True))
    if copy.fallback is not None:
        raise SystemExit(f"error: the direct copy fell back ({copy.fallback})")
    if backend.upload.fallback is not None:
        raise SystemExit(f"error: the direct upload fell back ({backend.upload.fallback})")
    nk = len(sim.engine_scene.engine.kinematic_names)
    kin = np.zeros((a.batch, 64, max(nk, 1), 6))
    steps = [np.full(a.batch, 1e-4), np.full(a.batch, 2e-4)]   # alternating, so that dt is sent every time

    def frame():
        steps.reverse()
        backend.set_frame(steps[0], np.full(a.batch, 64), kin, damage_on=True)

    cases = {"read_slots": {"to_numpy": (read, "forced"), "direct": (read, None),
                            "direct_into_reused_arrays": (read_reused, None), "fresh_pages_only": (fresh_pages, None)},
             "frame_end": {"to_numpy": (end, "forced"), "direct": (end, None)},
             "set_frame": {"from_numpy": (frame, "forced"), "direct": (frame, None)}}
    times: dict[str, dict[str, list[float]]] = {n: {k: [] for k in c} for n, c in cases.items()}
    for _ in range(a.repeats):
        for name, c in cases.items():
            for k, (fn, forced) in c.items():
                times[name][k].append(_timed(fn, forced, backend))
    backend.host_copy._fallback = backend.upload._fallback = None
    mb = sum(r.nbytes for r in ref) / 1e6
    summary = {name: {k: {"median_ms": float(np.median(v)) * 1e3, "ms": [x * 1e3 for x in v]} for k, v in t.items()}
               for name, t in times.items()}
    for name, s in summary.items():
        print(f"{name}: " + ", ".join(f"{k} {v['median_ms']:.2f} ms" for k, v in s.items()), flush=True)
    out = {"benchmark": "bench_host_reads", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "simulator_version": ident.version, "config_hash": ident.config, "preset": a.preset, "batch": a.batch,
           "slots_read": len(slots), "megabytes_read": mb, "device": backend.device, "repeats": a.repeats,
           "same_arrays": same,
           "frame_end_largest_relative_difference": end_diff, "times": summary}
    emit(out, a.out)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
