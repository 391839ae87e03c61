"""Refine on the simulator at dataset speed? Simulator seconds per run of a refine vs dataset generation.

Answers the first ``--limit`` rows of a target store with the bundle (top ``--starts`` candidates each),
then on one warm simulator: (1) ``invphys.inverter.refine.refine`` with ``--budget`` runs per target,
all targets in one open stream (``Simulator.simulate_feed``), (2) dataset generation of the very runs
the refine simulated (``simulate_stream``, the same slots, features extracted as runs end; with
``--random-dataset`` also as many uniformly random runs). Reports wall
seconds per run of each and their ratio, and R_actual before (the amortised answer; the best of its
starts) and after the refine. A simulator with its own ``simulate_feed`` (the AnisoMPM foods:
``Engine.stream_feed``, slots refilled as runs end) streams through it; ``--no-native-feed`` measures the
default instead (chunks of what is ready). Example (GPU)::

    python benchmarks/bench_refine.py --bundle inverters/orange_peel_paper \\
        --targets datasets/orange_peel_paper_fresh_uniform --limit 32 --budget 32 --sim-batch 64 \\
        --out benchmarks/results/refine_paper_h100.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def _machine() -> Any:
    if str(Path(__file__).parent) not in sys.path:
        sys.path.insert(0, str(Path(__file__).parent))
    import _machine

    return _machine


def use_default_feed(sim: Any) -> None:
    """Make ``sim`` stream through :meth:`Simulator.simulate_feed`'s default (chunks of the rows that are
    ready) even when it has its own open stream, to measure what that stream buys."""
    import types

    from invphys.core.interfaces import Simulator

    sim.simulate_feed = types.MethodType(Simulator.simulate_feed, sim)


def _recording(sim: Any) -> list[np.ndarray]:
    """Record the rows (physical) that ``sim.simulate_feed``'s feeders hand in, in feed order."""
    rows: list[np.ndarray] = []
    inner = sim.simulate_feed

    def simulate_feed(feeder: Any, batch_size: int | None = None) -> Any:
        def seen(free: int) -> Any:
            x = feeder(free)
            if x is not None and len(x):
                rows.extend(np.atleast_2d(x))
            return x

        return inner(seen, batch_size)

    sim.simulate_feed = simulate_feed
    return rows


def _dataset(sim: Any, ext: Any, params: np.ndarray, batch: int, pool: Any = None) -> dict[str, Any]:
    """Runs of ``params`` the way dataset generation runs them (``stream_rows``: continuous batching, features
    extracted as runs end, in ``pool``'s worker processes where one is given), wall time."""
    from invphys.plugins.executors._batch import stream_rows

    n = len(params)
    t0 = time.perf_counter()
    ok = sim_s = 0.0
    for _i, res in stream_rows(sim, ext, params, batch, pool=pool):
        ok += bool(res.ok and res.features is not None)
        sim_s += res.stats.wall_time_s if res.stats is not None else 0.0
    wall = time.perf_counter() - t0
    return {"runs": n, "ok": int(ok), "wall_s": wall, "s_per_run": wall / n, "simulator_s": sim_s}


def _summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    def mean(key: str) -> float | None:
        v = np.array([np.nan if r[key] is None else r[key] for r in records], float)
        v = np.where(np.isfinite(v), v, 0.0)   # a failed answer counts as R 0
        return float(v.mean()) if len(v) else None

    return {"r_answer": mean("r_answer"), "r_best_start": mean("start_r_actual"), "r_refined": mean("r_actual"),
            "improved": int(sum(r["improved"] for r in records)),
            "never_worse": bool(all(r["r_actual"] is not None and r["r_actual"] >= r["start_r_actual"]
                                    for r in records if r["start_r_actual"] is not None))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--bundle", default="inverters/orange_peel_paper")
    p.add_argument("--targets", default="datasets/orange_peel_paper_fresh_uniform", help="a store of target rows")
    p.add_argument("--limit", type=int, default=32)
    p.add_argument("--budget", type=int, default=32, help="simulator runs per target")
    p.add_argument("--starts", type=int, default=4, help="candidates per target the refine starts from")
    p.add_argument("--popsize", type=int, default=8)
    p.add_argument("--sigma0", type=float, default=0.012)
    p.add_argument("--method", default=None)
    p.add_argument("--sim-option", nargs="*", default=[], help="KEY=VALUE simulator overrides (e.g. arch=cpu)")
    p.add_argument("--sim-batch", type=int, default=64, help="runs in flight (slots) for both measurements")
    p.add_argument("--native-feed", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--skip-dataset", action="store_true", help="measure the refine only")
    p.add_argument("--random-dataset", action="store_true",
                   help="also time dataset generation of as many uniformly random runs")
    p.add_argument("--extract-workers", type=int, default=0,
                   help="feature-extraction processes for both measurements (0: in this process)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)

    import invphys
    from invphys.core.dataset import DatasetStore
    from invphys.inverter.refine import refine

    inv = invphys.load_inverter(a.bundle)
    rows = DatasetStore(a.targets).arrays(ok_only=True)
    y = rows.y[:a.limit]
    overrides = _machine().sim_options(a.sim_option)
    sim = inv.simulator(overrides)
    ext = inv.extractor(sim)
    from invphys.core.interfaces import Simulator

    own = type(sim).simulate_feed is not Simulator.simulate_feed
    if own and not a.native_feed:
        use_default_feed(sim)
    feed = ("the simulator's own (an open stream)" if own and a.native_feed
            else "default (chunks of ready rows)")
    t0 = time.perf_counter()
    results = inv.invert_many(y, method=a.method, top_k=a.starts, seed=a.seed)
    answer_s = time.perf_counter() - t0
    space = sim.parameter_space()
    rng = np.random.default_rng(a.seed + 1)
    pool = None
    if a.extract_workers:
        from invphys.plugins.executors._extract_pool import ExtractionPool

        pool = ExtractionPool(ext, a.extract_workers)
    warm = _dataset(sim, ext, space.denormalize(rng.random((a.sim_batch, space.dim))), a.sim_batch, pool)  # compiles
    fed = _recording(sim)
    t0 = time.perf_counter()
    records = refine(inv, results, a.budget, a.popsize, a.sigma0, overrides=overrides, batch_size=a.sim_batch,
                     seed=a.seed, simulator=sim, extract_workers=a.extract_workers)
    wall = time.perf_counter() - t0
    spent = sum(r["runs"] for r in records)
    # dataset generation of the very runs the refine simulated (same parameters, so the same cost per run)
    data = None if a.skip_dataset else _dataset(sim, ext, np.array(fed), a.sim_batch, pool)
    rand = _dataset(sim, ext, space.denormalize(rng.random((len(fed), space.dim))), a.sim_batch, pool) \
        if a.random_dataset else None
    if pool is not None:
        pool.close()
    ref = {"targets": len(y), "budget": a.budget, "starts": a.starts, "popsize": a.popsize, "sigma0": a.sigma0,
           "runs": spent, "wall_s": wall, "s_per_run": wall / max(spent, 1),
           "simulator_s": float(sum(r["simulator_s"] for r in records)), **_summary(records)}
    result = {"what": "refine on the simulator vs dataset generation, same warm simulator and slots",
              "device": _machine().simulator_device(sim), "simulator": sim.name, "simulator_version": sim.version,
              "simulator_config": sim.config.model_dump(), "overrides": overrides, "feed": feed,
              "bundle": a.bundle, "method": results[0].method if results else a.method, "targets": a.targets,
              "sim_batch": a.sim_batch, "extract_workers": a.extract_workers, "answer_s": answer_s, "warmup": warm, "dataset": data, "dataset_random": rand, "refine": ref,
              "refine_over_dataset": None if data is None else ref["s_per_run"] / data["s_per_run"],
              "per_target": [{k: v for k, v in r.items() if k not in ("call", "settings")} for r in records]}
    _machine().emit(result, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
