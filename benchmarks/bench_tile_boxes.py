"""How compact the tiled scatter's tiles stay as the orange deforms and tears (issue 16).

``p2g_tiled`` sums each tile of 256 consecutive device particles over the tile's bounding box of grid nodes
when that box holds at most ``TILE_NODES`` (1,024) nodes, and falls back to global atomics otherwise. The
device order is fixed when a run is loaded (a space-filling curve through the initial cells), so a tile
whose particles drift apart grows. This script simulates ``--runs`` random runs (seed 0) at ``--preset``,
then, for each recorded frame, computes every tile's box from the recorded positions: the share of tiles
that would scatter globally, and the median box, for the Morton and Hilbert orders of
the initial cells and for the Hilbert order of that frame's own cells (what re-sorting would give), and the
share of tiles over other box sizes (``LIMITS``: what a larger shared-memory box would keep tiled).
Geometry only: the kernels are not instrumented, so any GPU (or a CPU at ``--preset quick``) will do.

    python benchmarks/bench_tile_boxes.py --preset paper --runs 16 --out $OUT/tile_boxes_paper.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import shlex
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm", Path(__file__).parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import emit  # noqa: E402

#: box sizes (nodes) whose exceedance the report also gives: what a larger shared-memory box would catch
LIMITS = (1024, 1536, 1700, 2048, 4096)


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--runs", type=int, default=16)
    p.add_argument("--arch", default="cuda")
    p.add_argument("--every", type=int, default=10, help="analyse every n-th recorded frame")
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def tile_boxes(cells: np.ndarray, order: np.ndarray, tile: int = 256) -> np.ndarray:
    """Nodes in each tile's bounding box (the 3x3x3 stencil of every base cell) for device ``order``."""
    c = cells[order]
    n = len(c) // tile * tile
    full = c[:n].reshape(-1, tile, 3)
    boxes = (full.max(axis=1) - full.min(axis=1) + 3).prod(axis=1)
    if n < len(c):
        rest = c[n:]
        boxes = np.append(boxes, (rest.max(axis=0) - rest.min(axis=0) + 3).prod())
    return boxes


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys_anisompm.backends.particle_order import base_cells, hilbert_order, morton_order
    from invphys_anisompm.backends.taichi_backend import TILE, TILE_NODES
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.runs, space.dim)))
    sim = OrangePeelSimulator(backend="taichi", preset=a.preset, arch=a.arch, batch_size=a.runs)
    scene = sim.engine_scene
    o = scene.engine.options
    # the recorded trajectories are in the orange's particle order; the device orders index the engine's
    to_engine = scene.to_engine
    x0 = scene.engine.positions
    orders = {"morton": morton_order(x0, o.dx, o.grid), "hilbert": hilbert_order(x0, o.dx, o.grid)}
    results = sim.simulate(params)
    per_frame: dict[str, list[dict]] = {k: [] for k in (*orders, "hilbert_resorted")}
    for r in results:
        if not r.ok:
            continue
        pos = r.trajectory.positions[:, to_engine]
        for f in range(0, len(pos), a.every):
            cells = base_cells(pos[f], o.dx, o.grid)
            chosen = dict(orders, hilbert_resorted=hilbert_order(pos[f], o.dx, o.grid))
            for name, order in chosen.items():
                boxes = tile_boxes(cells, order, TILE)
                per_frame[name].append({"frame": int(r.trajectory.frame_indices[f]), "median_box": float(np.median(boxes)),
                                        "global_tiles": float((boxes > TILE_NODES).mean()),
                                        "over": {n: float((boxes > n).mean()) for n in LIMITS}})
    summary = {}
    for name, rows in per_frame.items():
        frames = sorted({row["frame"] for row in rows})
        by = {f: [row for row in rows if row["frame"] == f] for f in frames}
        summary[name] = {"frames": frames,
                         "global_tile_share": [float(np.mean([r["global_tiles"] for r in by[f]])) for f in frames],
                         "share_over_nodes": {str(n): [float(np.mean([r["over"][n] for r in by[f]])) for f in frames]
                                              for n in LIMITS},
                         "median_box": [float(np.median([r["median_box"] for r in by[f]])) for f in frames]}
        print(name, "global tile share by frame", [round(v, 3) for v in summary[name]["global_tile_share"]], flush=True)
    ident = RunIdentity.of(sim)
    out = {"benchmark": "bench_tile_boxes", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "simulator_version": ident.version, "config_hash": ident.config, "preset": a.preset, "runs": a.runs,
           "runs_ok": int(sum(r.ok for r in results)), "tile": TILE, "tile_nodes": TILE_NODES,
           "device": sim.engine.backend(a.runs).device, "orders": summary}
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
