"""What one Taichi kernel launch costs the host, by number of ndarray arguments (issue 16).

A substep is four kernel launches of 7-22 array arguments; with one or two runs active a substep costs the
host's ~0.2 ms of launches, not the GPU's work (``bench_active_runs``). This measures, for kernels that do
almost nothing (one thread adds to one element) and take ``--args`` ndarrays of shape (``--batch``,
``--particles``), the host's microseconds per launch from Python and from a Taichi graph of 8 launches,
and the wall microseconds per launch with one sync at the end (the GPU's floor when the host is faster).
If the cost grows with the arguments, fewer, packed arrays per stage would shorten the tail.

    python benchmarks/bench_launch_cost.py --args 1 4 8 16 24 --out $OUT/launch_cost_h100.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib.util
import shlex
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "examples" / "anisompm", Path(__file__).parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import emit  # noqa: E402


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--arch", default="cuda", help="cpu: a check of the script (times mean little there)")
    p.add_argument("--args", type=int, nargs="+", default=[1, 4, 8, 16, 24], help="ndarray arguments per kernel")
    p.add_argument("--launches", type=int, default=2000)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--particles", type=int, default=51104)
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def _kernel_module(counts: list[int], folder: Path):
    """A module with kernel ``k<m>`` per count ``m``: ``m`` ndarray arguments, one thread adds 1 to ``a0[0, 0]``
    (Taichi reads a kernel's source from its file, so the kernels are written to one)."""
    lines = ["import taichi as ti", ""]
    for m in counts:
        params = ", ".join(f"a{i}: ti.types.ndarray(ti.f32, 2)" for i in range(m))
        lines += ["@ti.kernel", f"def k{m}({params}):", "    for _ in range(1):", "        a0[0, 0] += 1.0", ""]
    path = folder / "launch_kernels.py"
    path.write_text("\n".join(lines))
    spec = importlib.util.spec_from_file_location("launch_kernels", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    import taichi as ti
    from invphys_anisompm.backends.taichi_backend import device_name, ensure_taichi
    from taichi import graph as tg

    arch = ensure_taichi(a.arch)
    arrays = [ti.ndarray(ti.f32, (a.batch, a.particles)) for _ in range(max(a.args))]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        module = _kernel_module(a.args, Path(tmp))
        for m in a.args:
            kern = getattr(module, f"k{m}")
            args = arrays[:m]
            kern(*args)
            ti.sync()
            t0 = time.perf_counter()
            for _ in range(a.launches):
                kern(*args)
            t1 = time.perf_counter()
            ti.sync()
            t2 = time.perf_counter()
            names = [f"a{i}" for i in range(m)]
            builder = tg.GraphBuilder()
            symbols = [tg.Arg(tg.ArgKind.NDARRAY, n, dtype=ti.f32, ndim=2) for n in names]
            for _ in range(8):
                builder.dispatch(kern, *symbols)
            graph = builder.compile()
            values = dict(zip(names, args, strict=True))
            graph.run(values)
            ti.sync()
            g0 = time.perf_counter()
            for _ in range(a.launches // 8):
                graph.run(values)
            g1 = time.perf_counter()
            ti.sync()
            g2 = time.perf_counter()
            n_graph = a.launches // 8 * 8
            row = {"ndarray_args": m, "python_host_us": (t1 - t0) / a.launches * 1e6,
                   "python_wall_us": (t2 - t0) / a.launches * 1e6, "graph_host_us": (g1 - g0) / n_graph * 1e6,
                   "graph_wall_us": (g2 - g0) / n_graph * 1e6}
            rows.append(row)
            print(f"{m:3d} arrays: python {row['python_host_us']:.1f} us host / {row['python_wall_us']:.1f} wall, "
                  f"graph {row['graph_host_us']:.1f} / {row['graph_wall_us']:.1f} us per launch", flush=True)
    out = {"benchmark": "bench_launch_cost", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "device": device_name(arch), "taichi": ".".join(map(str, ti.__version__)), "launches": a.launches,
           "array_shape": [a.batch, a.particles], "rows": rows}
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
