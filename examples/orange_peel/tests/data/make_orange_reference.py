"""Regenerate ``examples/orange_peel/tests/data/orange_peel_reference_tiny.npz``: the orange peel's features and per-frame series
at the ``tiny`` preset on the CPU, the reference that the engine-based simulator is held to.

The committed file was made with the orange peel's own kernels (simulator 0.2.0, before the port onto
``invphys-anisompm``; the commit is stored in the file). Usage::

    nice -n 19 .venv/bin/python examples/orange_peel/tests/data/make_orange_reference.py

Rows: the centre of the space, a weak skin (sigma_s = 0.05), a strong skin (sigma_s = 0.5) and four
fracturing vectors of the backend benchmark (seed 0, rows 4, 12, 13, 2); Taichi on the CPU, serialised
scatter, full tiny run (120 frames); Warp on the CPU for the first two rows.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

import numpy as np


def vectors(space) -> np.ndarray:
    def with_(**values: float) -> np.ndarray:
        return space.from_mapping(values, defaults=space.to_mapping(space.center()))

    bench = space.denormalize(np.random.default_rng(0).uniform(size=(16, space.dim))[[4, 12, 13, 2]])
    return np.vstack([space.center()[None], with_(sigma_s=0.05)[None], with_(sigma_s=0.5)[None], bench])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(Path(__file__).with_name("orange_peel_reference_tiny.npz")))
    ap.add_argument("--warp-rows", type=int, default=2)
    args = ap.parse_args()

    from invphys_orange_peel import SIMULATOR_VERSION
    from invphys_orange_peel.features import FEATURE_NAMES, OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator

    ext = OrangePeelFeatures()
    sim = OrangePeelSimulator(preset="tiny", arch="cpu", batch_size=7)
    params = vectors(sim.parameter_space())
    out: dict[str, np.ndarray] = {"params": params, "feature_names": np.array(FEATURE_NAMES)}
    for backend, rows in (("taichi", len(params)), ("warp", args.warp_rows)):
        s = OrangePeelSimulator(backend=backend, preset="tiny", arch="cpu", batch_size=rows)
        res = s.simulate(params[:rows])
        assert all(r.ok for r in res), [r.failure for r in res]
        out[f"{backend}_features"] = np.stack([ext.extract(r.trajectory) for r in res])
        out[f"{backend}_substeps"] = np.array([r.stats.substeps for r in res])
        for key in ("frame_separation", "frame_mean_damage", "frame_work", "max_speed", "kinetic_energy"):
            out[f"{backend}_{key}"] = np.stack([np.asarray(r.trajectory.extra[key], np.float64) for r in res])
        out[f"{backend}_final_positions"] = np.stack([r.trajectory.positions[-1] for r in res])
        out[f"{backend}_final_damage"] = np.stack([r.trajectory.damage[-1] for r in res])
        print(backend, "done", flush=True)
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    out["made_with"] = np.array(f"invphys_orange_peel {SIMULATOR_VERSION} own kernels, commit {commit}")
    np.savez_compressed(args.out, **out)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
