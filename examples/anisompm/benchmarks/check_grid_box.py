"""Check on a GPU that each run's node boxes hold its whole grid (issue 16; the CPU test is
``tests/test_taichi_grid_box.py``, which cannot run the tiled scatter).

The Taichi backend's grid clear and update read only the nodes of each run's scatter box (``BOX_LAST``,
``BOX_NEXT``); the tiled scatter grows the box from its tiles' node boxes. This simulates ``--frames`` frames of
a random batch (a deformed, fractured state), then launches ``--steps`` substeps stage by stage and checks after
each one, for every active run, that the box is exactly the nodes its particles' scatter touches (computed on
the host from the positions) and that no node outside it holds anything.

    python examples/anisompm/benchmarks/check_grid_box.py --preset paper --batch 16 --frames 60 --out grid_box_paper.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import shlex
import sys
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
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--arch", default="cuda")
    p.add_argument("--frames", type=int, default=60, help="frames simulated before the checked substeps")
    p.add_argument("--steps", type=int, default=30, help="substeps checked one by one")
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def scatter_box(x: np.ndarray, dx: float, G: int) -> np.ndarray:
    """The node box (lo xyz, hi xyz) a scatter of positions ``x`` (N, 3) touches, as the kernels compute it."""
    inv_dx = np.float32(1.0) / np.float32(dx)
    base = np.clip((x.astype(np.float32) * inv_dx - np.float32(0.5)).astype(np.int32), 0, G - 3)
    return np.concatenate([base.min(0), base.max(0) + 2])


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys_anisompm.backends.taichi_backend import BOX_LAST
    from invphys_orange_peel.engine_scene import model_for
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.batch, space.dim)))
    sim = OrangePeelSimulator(backend="taichi", preset=a.preset, arch=a.arch, batch_size=a.batch)
    backend = sim.engine.backend(a.batch)
    model = model_for(sim.engine_scene, params)
    if a.frames:
        sim.engine.run(model, a.frames, a.frames)   # leaves the batch's state at frame a.frames
    else:
        backend.load(model.table(), model.friction)
    o = backend.options
    G = o.grid
    nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
    B = a.batch
    backend.set_frame(np.full(B, 2e-5), np.full(B, a.steps), np.zeros((B, a.steps, nk, 6)), damage_on=True)
    violations, volumes = [], []
    for k in range(a.steps):
        expected = [scatter_box(x, o.dx, G) for x in backend.x.to_numpy()]
        for launch in backend._stages(k).values():
            launch()
        box = backend.box.to_numpy()
        held = (backend.gm.to_numpy() != 0) | (backend.gd.to_numpy() != 0).any(-1) | (backend.gv.to_numpy() != 0).any(-1)
        for b in range(B):
            last = box[b, BOX_LAST]
            nodes = np.argwhere(held[b])
            outside = int((np.any(nodes < last[:3], axis=1) | np.any(nodes > last[3:], axis=1)).sum())
            if not np.array_equal(last, expected[b]) or outside:
                violations.append({"substep": k, "run": b, "box": last.tolist(), "expected": expected[b].tolist(),
                                   "nodes_outside": outside})
            volumes.append(float(np.prod(last[3:] - last[:3] + 1)) / G ** 3)
    ok = not violations
    print(f"{'OK' if ok else 'VIOLATIONS'}: {len(violations)} of {a.steps * B} run-substeps; box volume "
          f"{np.mean(volumes):.3f} of the grid on average (max {np.max(volumes):.3f})", flush=True)
    ident = RunIdentity.of(sim)
    out = {"benchmark": "check_grid_box", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
           "simulator_version": ident.version, "config_hash": ident.config, "device": backend.device,
           "scatter": backend.p2g, "preset": a.preset, "batch": B, "frames": a.frames, "steps": a.steps, "ok": ok,
           "box_volume_share_mean": float(np.mean(volumes)), "box_volume_share_max": float(np.max(volumes)),
           "violations": violations[:20]}
    emit(out, a.out)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
