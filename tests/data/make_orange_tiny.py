"""Regenerate ``tests/data/orange_tiny.npz``: real orange-peel runs at the ``tiny`` preset.

Usage (slow on a CPU; run it with low priority)::

    nice -n 19 .venv/bin/python tests/data/make_orange_tiny.py --n 240 --batch 16 --out tests/data/orange_tiny.npz

The committed fixture was made on a GPU machine with ``--n 512 --batch 64 --arch cuda`` (a 2-core CPU
shared with other work managed only a few runs a minute).

Parameters are a scrambled Sobol sample of [0,1]^9 (seeded), mapped to physical units with the
simulator's parameter space; each run's features come from the simulator's default extractor. Rows
whose run failed are kept out of ``theta``/``y`` and counted in ``n_failed``. The file is rewritten
after every batch, so an interrupted run leaves a usable (smaller) fixture; ``--resume`` continues it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=240)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", default="taichi")
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--out", default=str(Path(__file__).with_name("orange_tiny.npz")))
    ap.add_argument("--resume", action="store_true")
    args = ap.parse_args()

    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator
    from scipy.stats import qmc

    sim = OrangePeelSimulator(backend=args.backend, preset=args.preset, arch=args.arch, batch_size=args.batch)
    ext = OrangePeelFeatures()
    space = sim.parameter_space()
    m = 1 << int(np.ceil(np.log2(args.n)))
    theta_all = qmc.Sobol(d=space.dim, scramble=True, seed=args.seed).random(m)[: args.n]
    out = Path(args.out)
    done = {"theta": [], "params": [], "y": [], "wall": [], "substeps": []}
    failed: list[dict[str, object]] = []
    start = 0
    if args.resume and out.exists():
        old = np.load(out, allow_pickle=False)
        start = int(old["n_attempted"])
        for k in ("theta", "params", "y"):
            done[k] = list(old[k])
        done["wall"] = list(old["wall_time_s"])
        done["substeps"] = list(old["substeps"])
        failed = json.loads(str(old["failures"]))
    t0 = time.time()
    for b in range(start, args.n, args.batch):
        theta = theta_all[b:b + args.batch]
        params = space.denormalize(theta)
        results = sim.simulate(params)
        for th, res in zip(theta, results, strict=True):
            if res.ok:
                done["theta"].append(th)
                done["params"].append(res.params)
                done["y"].append(ext.extract(res.trajectory))
                done["wall"].append(res.stats.wall_time_s)
                done["substeps"].append(res.stats.substeps)
            else:
                failed.append({"theta": th.tolist(), "failure": res.failure})
        n_att = min(b + args.batch, args.n)
        _write(out, done, failed, n_att, args, sim, ext)
        print(f"{n_att}/{args.n} runs, {len(done['y'])} ok, {len(failed)} failed, {time.time() - t0:.0f} s",
              flush=True)


def _source_hash() -> str:
    """sha256 (16 hex) of the simulator package's Python sources: which code made the data."""
    import hashlib

    import invphys_orange_peel

    h = hashlib.sha256()
    for f in sorted(Path(invphys_orange_peel.__file__).parent.rglob("*.py")):
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _write(out: Path, done: dict, failed: list, n_att: int, args: argparse.Namespace, sim, ext) -> None:
    prov = {"simulator": sim.name, "simulator_version": sim.version, "source_sha256": _source_hash(),
            "preset": args.preset,
            "backend": args.backend, "arch": args.arch, "sampler": "sobol(scrambled)", "seed": args.seed,
            "n_requested": args.n, "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "config": sim.config.model_dump(mode="json")}
    tmp = out.with_name(out.stem + ".tmp.npz")
    np.savez_compressed(
        tmp, theta=np.asarray(done["theta"], np.float64).reshape(-1, 9),
        params=np.asarray(done["params"], np.float64).reshape(-1, 9),
        y=np.asarray(done["y"], np.float64).reshape(len(done["y"]), -1),
        feature_names=np.asarray(ext.feature_names), param_names=np.asarray(sim.parameter_space().names),
        wall_time_s=np.asarray(done["wall"], np.float64), substeps=np.asarray(done["substeps"], np.int64),
        n_attempted=np.int64(n_att), failures=np.asarray(json.dumps(failed)),
        preset=np.asarray(args.preset), backend=np.asarray(args.backend),
        simulator_version=np.asarray(sim.version), provenance=np.asarray(json.dumps(prov)))
    tmp.replace(out)


if __name__ == "__main__":
    main()
