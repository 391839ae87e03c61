"""How fast the amortised answer is, batched, and where its time goes: ``Inverter.invert_many`` on fresh targets.

    python benchmarks/bench_pool_speed.py --bundle inverters/orange_peel_paper_all \\
        --targets uniform=datasets/orange_peel_paper_fresh_uniform edge=datasets/orange_peel_paper_fresh_edge \\
        --methods default pool_nsf4 --workers 2 --out benchmarks/results/pool_speed_paper_all_cpu.json

Every set is answered as one batch (``invert_many``, the default interval draws) ``--repeat`` times per
method; the fastest repeat counts (the machine may be shared). Per method and set: milliseconds per
target, and per stage (exclusive time, milliseconds per target):

* ``draws <label>``: posterior draws of each flow (the method's own NPE and a pool's ``extra`` members);
* ``neighbour search``: the stored rows nearest each target;
* ``surrogate scoring``: the ensemble on the candidates (and the exact R of stored rows);
* ``moves``: the local moves' starts and steps;
* ``candidate assembly``: the pool's own work between those (or a posterior method's choice);
* ``uncertainty``: the draws' recalibration (the intervals);
* ``result objects``: candidates, error bars, warnings and the :class:`InversionResult` per target;
* ``other``: the rest (conditions, seeds, batching).

``--workers N``: all sets together answered by N worker processes (``invert_many(workers=N)``): the first call
(processes started, each loading the bundle) and the fastest later call (processes kept), per method.

No simulator runs: the answers are only timed. ``default`` is the bundle's default method. ``flow_inverse``
says which code drew each flow's rows: invphys' spline sampler (sbi's ``nsf``, the same bits as nflows'
inverse; tests/test_npe_draw_speed.py) or nflows' own inverse.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np


def _machine() -> Any:
    if str(Path(__file__).parent) not in sys.path:
        sys.path.insert(0, str(Path(__file__).parent))
    import _machine

    return _machine


class Stages:
    """Exclusive wall time per stage of wrapped functions (a stage's time less its wrapped callees')."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._stack: list[float] = []
        self._undo: list[tuple[Any, str, Any]] = []

    def wrap(self, owner: Any, name: str, stage: str | Callable[[tuple[Any, ...]], str]) -> None:
        f = owner.__dict__.get(name) if isinstance(owner, type) else getattr(owner, name, None)
        if f is None:  # not in this version (or inherited: its owner is wrapped)
            return

        def timed(*args: Any, **kw: Any) -> Any:
            label = stage(args) if callable(stage) else stage
            t0 = time.perf_counter()
            self._stack.append(0.0)
            try:
                return f(*args, **kw)
            finally:
                dt = time.perf_counter() - t0
                self.seconds[label] += dt - self._stack.pop()
                if self._stack:
                    self._stack[-1] += dt

        setattr(owner, name, timed)
        self._undo.append((owner, name, f))

    def restore(self) -> None:
        for owner, name, f in reversed(self._undo):
            setattr(owner, name, f)
        self._undo.clear()


def instrument(inv: Any) -> Stages:
    """Wrap the answer's stages (whatever of them this version of invphys has)."""
    from invphys.inverter import answers, draws, inverter, pool

    st = Stages()

    def flow_label(args: tuple[Any, ...]) -> str:
        for label, (plugin, _) in inv._plugins.items():
            if plugin is args[0]:
                return f"draws {label}"
        return "draws"

    st.wrap(draws, "sample_posterior", flow_label)
    st.wrap(pool, "nearest_rows", "neighbour search")
    for name in ("score", "stored_score", "score_many"):
        st.wrap(pool.PoolAnswers, name, "surrogate scoring")
    st.wrap(pool.PoolAnswers, "_moves", "moves")
    for cls in (pool.PoolAnswers, answers.PosteriorAnswers):
        st.wrap(cls, "from_draws", "candidate assembly")
    st.wrap(answers.PosteriorAnswers, "_choose", "candidate assembly")
    st.wrap(inverter, "recalibrated", "uncertainty")
    st.wrap(inverter.Inverter, "_answer_one", "result objects")
    return st


def _targets(specs: list[str], limit: int | None) -> dict[str, np.ndarray]:
    from invphys.core.dataset import DatasetStore

    out = {}
    for spec in specs:
        name, _, path = spec.partition("=")
        y = DatasetStore(path).arrays(ok_only=True).y
        out[name] = y[:limit] if limit else y
    return out


def time_method(inv: Any, method: str, sets: dict[str, np.ndarray], repeat: int, seed: int,
                kw: dict[str, Any]) -> dict[str, Any]:
    """Per set: the fastest of ``repeat`` batched answers, ms per target, and its stages."""
    out: dict[str, Any] = {}
    inv.invert_many(next(iter(sets.values()))[:2], method=method, seed=seed, **kw)  # networks loaded, caches warm
    for name, y in sets.items():
        best: tuple[float, dict[str, float]] | None = None
        for _ in range(repeat):
            st = instrument(inv)
            t0 = time.perf_counter()
            try:
                inv.invert_many(y, method=method, seed=seed, **kw)
            finally:
                st.restore()
            total = time.perf_counter() - t0
            if best is None or total < best[0]:
                stages = dict(st.seconds)
                stages["other"] = total - sum(stages.values())
                best = (total, stages)
        assert best is not None
        out[name] = {"targets": len(y), "ms_per_target": round(1000 * best[0] / len(y), 3),
                     "stages_ms_per_target": {k: round(1000 * v / len(y), 3) for k, v in
                                              sorted(best[1].items(), key=lambda kv: -kv[1])}}
    return out


def time_workers(inv: Any, method: str, y: np.ndarray, workers: int, repeat: int, seed: int,
                 kw: dict[str, Any]) -> dict[str, Any]:
    """All targets ``y`` in one ``invert_many(workers=...)`` call: the first call (processes started, each
    loading the bundle) and the fastest of ``repeat`` later calls (the processes kept), ms per target."""
    from invphys.inverter.parallel import close_workers

    def once() -> float:
        t0 = time.perf_counter()
        inv.invert_many(y, method=method, seed=seed, workers=workers, **kw)
        return time.perf_counter() - t0

    close_workers(inv)   # a cold first call, whatever ran before
    first = once()
    later = min(once() for _ in range(repeat))
    return {"workers": workers, "targets": len(y), "first_call_ms_per_target": round(1000 * first / len(y), 3),
            "later_calls_ms_per_target": round(1000 * later / len(y), 3)}


def flow_inverse(inv: Any) -> dict[str, str]:
    """Per posterior method the answers drew from: which code ran its flow's inverse."""
    from invphys.inverter import draws
    from invphys.plugins.baselines.spline_sampler import spline_sampler

    out = {}
    for label, (plugin, _) in sorted(inv._plugins.items()):
        if draws.has_posterior(plugin):
            net = draws._flow(plugin._posterior.posterior_estimator)
            out[label] = ("sbi sample" if net is None else
                          "invphys spline sampler" if spline_sampler(net) is not None else "nflows inverse")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bundle", default="inverters/orange_peel_paper_all")
    p.add_argument("--targets", nargs="+", default=["uniform=datasets/orange_peel_paper_fresh_uniform",
                                                     "edge=datasets/orange_peel_paper_fresh_edge"])
    p.add_argument("--methods", nargs="+", default=["default", "pool_nsf4"])
    p.add_argument("--limit", type=int, default=None, help="targets per set (default: all)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--draws", type=int, default=None, help="interval draws per target (default: invert's)")
    p.add_argument("--flow-threads", type=int, default=None, help="torch threads while drawing (default: draws.THREADS)")
    p.add_argument("--workers", type=int, nargs="*", default=[],
                   help="also time all targets answered by N worker processes (invert_many(workers=N))")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    import torch

    import invphys
    from invphys.inverter import draws

    if a.flow_threads:
        draws.THREADS = a.flow_threads
    inv = invphys.load_inverter(a.bundle)
    sets = _targets(a.targets, a.limit)
    kw = {} if a.draws is None else {"draws": a.draws}
    methods = list(dict.fromkeys(inv.default_method if m == "default" else m for m in a.methods))
    load0 = os.getloadavg()
    results = {m: time_method(inv, m, sets, a.repeat, a.seed, kw) for m in methods}
    for r in results.values():
        n = sum(v["targets"] for v in r.values())
        r["all"] = {"targets": n, "ms_per_target": round(sum(v["ms_per_target"] * v["targets"]
                                                             for v in r.values()) / n, 3)}
    y_all = np.concatenate(list(sets.values()))
    for meth, r in results.items():
        for w in a.workers:
            r.setdefault("workers", []).append(time_workers(inv, meth, y_all, w, a.repeat, a.seed, kw))
    m = _machine()
    m.emit({"device": f"cpu ({m.cpu_name()}), {os.cpu_count()} cores", "bundle": a.bundle,
            "default_method": inv.default_method, "targets": {k: len(v) for k, v in sets.items()},
            "repeat": a.repeat, "interval_draws": a.draws or "invert's default (256)", "flow_threads": draws.THREADS,
            "torch_threads": torch.get_num_threads(), "flow_inverse": flow_inverse(inv),
            "load_average": {"before": [round(x, 2) for x in load0], "after": [round(x, 2) for x in os.getloadavg()]},
            "methods": results}, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
