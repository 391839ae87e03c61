"""Host microseconds of a continuous-batching slot's frame start (issue 16): the velocity guard and the kinematic
table of one run, on the orange peel's paper scene.

Continuous batching starts a slot's next frame on the host while the GPU waits (``streaming.begin_frame``); a
cProfile of 256 paper runs on an H100 host put it at 4.1 s of a 67 s wall (65,344 frame starts, 12,512 kinematic
tables built). This times its two costly parts: ``velocity_guard`` on one-run arrays against ``velocity_guard_one``
(Python floats; absent before stop 40) and ``kinematic_table`` for one run of ``--substeps``. Run it with an older
``invphys_anisompm`` first on ``PYTHONPATH`` to compare versions (the host's CPU is the device here).

    python benchmarks/bench_frame_start_host.py --out benchmarks/results/frame_start_host_cpu.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import shlex
import sys
import timeit
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm", Path(__file__).parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import cpu_name, emit  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--substeps", type=int, default=37, help="substeps of the frame (the paper runs' mean is ~24)")
    ap.add_argument("--repeat", type=int, default=3000)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    import invphys_anisompm.engine as engine
    from invphys_orange_peel.simulator import OrangePeelSimulator

    scene = OrangePeelSimulator(preset=a.preset, arch="cpu").engine_scene.engine
    o = scene.options

    def per_call(fn) -> float:
        return timeit.timeit(fn, number=a.repeat) / a.repeat * 1e6

    nsub, vmax = np.array([a.substeps]), np.array([0.8])
    row: dict = {"velocity_guard_one_run_arrays_us": per_call(
        lambda: engine.velocity_guard(nsub, vmax, o.dx, o.fps, o.velocity_cfl))}
    if hasattr(engine, "velocity_guard_one"):
        row["velocity_guard_one_us"] = per_call(
            lambda: engine.velocity_guard_one(a.substeps, 0.8, o.dx, o.fps, o.velocity_cfl))
    dts = (1.0 / o.fps) / nsub
    row["kinematic_table_one_run_us"] = per_call(
        lambda: engine.kinematic_table(scene, 100, nsub, dts, np.ones(1, bool)))
    print(row, flush=True)
    out = {"benchmark": "bench_frame_start_host", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "device": f"cpu:{cpu_name()}x{os.cpu_count()}", "engine": engine.__file__, "preset": a.preset,
           "substeps": a.substeps, "repeat": a.repeat, "row": row}
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
