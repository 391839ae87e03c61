"""One-at-a-time parameter sweep of the orange peel: which parameters move which features.

Runs the centre of the normalised space and, for each of the 9 parameters, its two extremes with the
others at the centre (19 runs in one batch), and writes the features to
``benchmarks/results/simulator_sweep_<preset>.json``::

    python benchmarks/bench_simulator_sweep.py --preset tiny
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


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--backend", default="taichi", choices=["taichi", "warp"])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator

    sim = OrangePeelSimulator(preset=args.preset, arch=args.arch, backend=args.backend, batch_size=32)
    space = sim.parameter_space()
    rows, names = [np.full(space.dim, 0.5)], ["centre"]
    for j, name in enumerate(space.names):
        for value in (0.0, 1.0):
            u = np.full(space.dim, 0.5)
            u[j] = value
            rows.append(u)
            names.append(f"{name}={space.denormalize(u)[j]:g}")
    t0 = time.perf_counter()
    results = sim.simulate(space.denormalize(np.array(rows)))
    wall = time.perf_counter() - t0
    ex = OrangePeelFeatures()
    out = {"benchmark": "bench_simulator_sweep", "preset": args.preset, "backend": args.backend,
           "device": results[0].stats.device, "wall_s": wall, "features": list(ex.feature_names),
           "runs": {n: {"ok": r.ok, "failure": r.failure, "substeps": r.stats.substeps,
                        "params": space.to_mapping(r.params),
                        "features": ex.extract(r.trajectory).tolist() if r.ok else None}
                    for n, r in zip(names, results, strict=True)}}
    path = args.out or ROOT / "benchmarks" / "results" / f"simulator_sweep_{args.preset}.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"{'run':16s} " + " ".join(f"{f[:10]:>10s}" for f in ex.feature_names))
    for n, r in out["runs"].items():
        vals = " ".join(f"{v:10.4g}" for v in r["features"]) if r["features"] else r["failure"]
        print(f"{n:16s} {vals}")
    return out


if __name__ == "__main__":
    main()
