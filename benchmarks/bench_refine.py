"""Refine on the simulator at dataset speed? Simulator seconds per run of a refine vs dataset generation.

Answers the first ``--limit`` rows of a target store with the bundle (top ``--starts`` candidates each),
then on one warm simulator: (1) ``invphys.inverter.refine.refine`` with ``--budget`` runs per target,
all targets in one open stream (``Simulator.simulate_feed``), (2) dataset generation of the very runs
the (first) refine simulated (``simulate_stream``, the same slots, features extracted as runs end; with
``--random-dataset`` also as many uniformly random runs; ``--dataset-runs N``: of the refine's first N runs
only). Reports wall seconds per run of each and their ratio, and R_actual before (the amortised answer; the
best of its starts) and after the refine. A simulator with its own ``simulate_feed`` (the AnisoMPM foods:
``Engine.stream_feed``, slots refilled as runs end) streams through it; ``--no-native-feed`` measures the
default instead (chunks of what is ready). Example (GPU)::

    python benchmarks/bench_refine.py --bundle inverters/orange_peel_paper \\
        --targets datasets/orange_peel_paper_fresh_uniform --limit 32 --budget 32 --sim-batch 64 \\
        --out benchmarks/results/refine_paper_h100.json

Several ``--strategy`` (e.g. ``cma corrected``) refine the same targets from the same starts on the one
warm simulator; ``--targets uniform=PATH edge=PATH`` names several target sets. Per set and strategy:
mean R_actual (refined, best start) with 95 % bootstrap intervals over targets, the runs, time and
per-target records, and each strategy's paired difference to the first (``sets.<name>.paired``); the JSON
is written after every strategy, so a stopped run keeps what it measured. Each strategy's block also gives
the mean runs a target used (``--stop``: a target stops at that R_actual; default the refine's own),
simulator-seconds per target, the targets that stopped, the mean best R_actual after 16, 32, 48, ... runs
of each target's ask-ordered runs (``r_at_runs``; a target that stopped earlier keeps its final best) and the
seconds its searches spent proposing points between runs (``ask_s``; ``ask_cpu_s``: their CPU seconds, much
less than ``ask_s`` when the asks waited for the GIL or a core), and the seconds the stream had free slots and
nothing to feed because an ask was pending (``ask_wait_s``; ``--ask-workers 0`` asks between launches, as
before, and every ask holds the stream). ``--first N --limit M`` takes targets N .. N+M-1 of each set: shards
of one set on several processes or GPUs. ``--extract-threads`` is each extraction worker's BLAS/OpenMP threads.
``--log-dir DIR`` keeps every refine's runs (a run cut short by a time limit resumes from them: the same command
replays the logged runs and simulates the rest). ``--patience N --min-gain D``: a target also stops once its best R_actual gained < D over its last N told runs
(the refine's stall rule; off by default); the result records both, each strategy's ``stalled`` count, and
per target ``stalled`` and ``batches`` (its told generations' sizes), which
``benchmarks/bench_refine_replay.py`` uses to replay stop rules exactly. ``--answers-out FILE`` only answers
(no simulator; e.g. on a CPU with sbi) and writes each target's starts; ``--answers-in FILE`` refines those
starts instead of answering (a GPU machine without sbi), the same refine as answering there.
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


def bootstrap(v: np.ndarray, n: int = 2000, seed: int = 0) -> dict[str, float | None]:
    """Mean of ``v`` and its 95 % percentile bootstrap interval (resampling targets; seeded)."""
    v = np.asarray(v, float)
    if not len(v):
        return {"mean": None, "lo": None, "hi": None}
    idx = np.random.default_rng(seed).integers(0, len(v), (n, len(v)))
    means = v[idx].mean(1)
    return {"mean": float(v.mean()), "lo": float(np.percentile(means, 2.5)), "hi": float(np.percentile(means, 97.5))}


def _r_values(records: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.array([0.0 if r[key] is None else r[key] for r in records], float)   # a failed answer counts as 0


def r_at_runs(records: list[dict[str, Any]], budget: int, step: int = 16) -> dict[str, float]:
    """Mean over targets of the best R_actual after n runs (n = step, 2 step, ..., and the budget), from each
    target's ``best_r_by_run`` (fewer runs, e.g. stopped: its last value; none or failed: 0)."""
    out = {}
    for n in sorted({*range(step, budget + 1, step), budget}):
        vals = []
        for r in records:
            by = r.get("best_r_by_run") or []
            v = by[min(n, len(by)) - 1] if by else r["r_actual"]
            vals.append(0.0 if v is None else float(v))
        out[str(n)] = float(np.mean(vals)) if vals else float("nan")
    return out


def _strategy_block(records: list[dict[str, Any]], wall: float, n_boot: int) -> dict[str, Any]:
    """One strategy on one target set: means with intervals, runs, time, per-target records."""
    spent = sum(r["runs"] for r in records)
    n = max(len(records), 1)
    ask = float(sum(r.get("ask_s", 0.0) for r in records))
    call = records[0].get("call", {}) if records else {}
    return {"runs": spent, "wall_s": wall, "s_per_run": wall / max(spent, 1),
            "simulator_s": float(sum(r["simulator_s"] for r in records)), **_summary(records),
            "runs_per_target": spent / n, "simulator_s_per_target": float(sum(r["simulator_s"] for r in records)) / n,
            "stopped": int(sum(bool(r.get("stopped")) for r in records)),
            "stalled": int(sum(bool(r.get("stalled")) for r in records)),
            "capped": int(sum(bool(r.get("capped")) for r in records)),
            "r_at_runs": r_at_runs(records, records[0]["budget"] if records else 0),
            "ask_s": ask, "ask_s_per_run": ask / max(spent, 1),
            "ask_cpu_s": float(sum(r.get("ask_cpu_s", 0.0) for r in records)),
            "ask_wait_s": call.get("ask_wait_s"), "ask_workers": call.get("ask_workers"),
            "r_refined_ci": bootstrap(_r_values(records, "r_actual"), n_boot),
            "r_best_start_ci": bootstrap(_r_values(records, "start_r_actual"), n_boot),
            "below_half": int(sum(r["warning"] is not None for r in records)),
            "target_done_s": _done_s(records),
            "per_target": [{k: v for k, v in r.items() if k not in ("call",)} for r in records]}


def _done_s(records: list[dict[str, Any]]) -> dict[str, float] | None:
    """When the targets' last generations came back (seconds into the refine): the median, 90th percentile and
    last target against the wall time show whether a refine is bound by its longest chains of generations."""
    done = [r["generations_back_s"][-1] for r in records if r.get("generations_back_s")]
    if not done:
        return None
    return {"median": float(np.median(done)), "p90": float(np.percentile(done, 90)), "max": float(max(done))}


def _paired(blocks: dict[str, dict[str, Any]], n_boot: int) -> dict[str, Any]:
    """Each strategy minus the first, per target (same targets and starts), with a bootstrap interval."""
    names = list(blocks)
    base = _r_values(blocks[names[0]]["per_target"], "r_actual")
    return {f"{s} - {names[0]}": bootstrap(_r_values(blocks[s]["per_target"], "r_actual") - base, n_boot, seed=1)
            for s in names[1:]}


def _target_sets(specs: list[str]) -> dict[str, str]:
    """``NAME=PATH`` or ``PATH`` (named after its folder) target stores, in order."""
    out: dict[str, str] = {}
    for spec in specs:
        name, eq, path = spec.partition("=")
        if not eq:
            name, path = Path(spec).name, spec
        if name in out:
            raise SystemExit(f"error: target set {name!r} given twice")
        out[name] = path
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--bundle", default="inverters/orange_peel_paper")
    p.add_argument("--targets", nargs="+", default=["datasets/orange_peel_paper_fresh_uniform"],
                   help="target stores: PATH or NAME=PATH (several: e.g. uniform=PATH edge=PATH)")
    p.add_argument("--first", type=int, default=0, help="skip the first N targets of each set (with --limit: a shard)")
    p.add_argument("--limit", type=int, default=32)
    p.add_argument("--budget", type=int, default=32, help="simulator runs per target")
    p.add_argument("--starts", type=int, default=4, help="candidates per target the refine starts from")
    p.add_argument("--strategy", nargs="+", default=["cma"], choices=["cma", "corrected"],
                   help="refine strategies, each on the same targets and starts (paired against the first)")
    p.add_argument("--known-starts", type=int, default=None,
                   help="stored training rows added as free starts (default: the strategy's own)")
    p.add_argument("--strategy-option", nargs="*", default=[], help="KEY=VALUE options of the corrected strategy")
    p.add_argument("--stop", type=float, default=None,
                   help="a target stops once its R_actual reaches this (0: never; default: the refine's own)")
    p.add_argument("--patience", type=int, default=None,
                   help="a target stops once its best R gained < --min-gain over its last N runs (default: off)")
    p.add_argument("--min-gain", type=float, default=None, help="the stall rule's gain (default: the refine's own)")
    p.add_argument("--cost-budget", type=float, default=None,
                   help="a target's most estimated simulator cost, in typical runs (default: none)")
    p.add_argument("--popsize", type=int, default=8)
    p.add_argument("--sigma0", type=float, default=0.012)
    p.add_argument("--method", default=None)
    p.add_argument("--sim-option", nargs="*", default=[], help="KEY=VALUE simulator overrides (e.g. arch=cpu)")
    p.add_argument("--sim-batch", type=int, default=64, help="runs in flight (slots) for both measurements")
    p.add_argument("--native-feed", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--skip-dataset", action="store_true", help="measure the refine only")
    p.add_argument("--dataset-runs", type=int, default=None,
                   help="time dataset generation on the first N runs the refine fed (default: all of them)")
    p.add_argument("--random-dataset", action="store_true",
                   help="also time dataset generation of as many uniformly random runs")
    p.add_argument("--extract-workers", type=int, default=0,
                   help="feature-extraction processes for both measurements (0: in this process)")
    p.add_argument("--extract-threads", type=int, default=1,
                   help="BLAS/OpenMP threads per extraction process (0: the libraries' default, one per core)")
    p.add_argument("--ask-workers", type=int, default=1,
                   help="threads asking the searches while the simulator runs (0: between launches)")
    p.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples of the intervals")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--log-dir", type=Path, default=None,
                   help="keep each (set, strategy) refine's runs in DIR/refine_<set>_<strategy>_<first>.npz: a run "
                        "stopped early (a time limit) is resumed by the same command, its logged runs replayed "
                        "(counted in replayed_runs; the timings then cover the new runs only)")
    p.add_argument("--answers-out", type=Path, default=None,
                   help="answer only (no simulator): write each target's starts to this JSON file and stop")
    p.add_argument("--answers-in", type=Path, default=None,
                   help="refine the starts of an --answers-out file instead of answering (no sbi needed)")
    p.add_argument("--out", type=Path, default=None)
    return p


def _answer_sets(inv: Any, sets: dict[str, str], a: argparse.Namespace) -> dict[str, Any]:
    """Per set: its targets' features and the bundle's answers (``--starts`` candidates each), or the starts
    an ``--answers-in`` file gave for the same targets, re-scored as candidates by this bundle."""
    from invphys.core.dataset import DatasetStore

    given_method, given = _read_starts(a.answers_in, a) if a.answers_in else (None, {})
    out: dict[str, Any] = {}
    for name, path in sets.items():
        y = DatasetStore(path).arrays(ok_only=True).y[a.first:a.first + a.limit]
        t0 = time.perf_counter()
        if name in given:
            starts = given[name]
            if len(starts) != len(y):
                raise SystemExit(f"error: {a.answers_in} holds {len(starts)} targets of set {name!r}, not {len(y)}")
            results = [inv.evaluate(theta=t, target=v, label=given_method or "given")
                       for t, v in zip(starts, y, strict=True)]
        elif a.answers_in:
            raise SystemExit(f"error: {a.answers_in} holds no set {name!r}")
        else:
            results = inv.invert_many(y, method=a.method, top_k=a.starts, seed=a.seed)
        out[name] = (y, results, time.perf_counter() - t0)
    return out


def _read_starts(path: Path, a: argparse.Namespace) -> tuple[str | None, dict[str, list[np.ndarray]]]:
    """(the method that answered, each set's starts per target) of an ``--answers-out`` file for these targets."""
    import json

    data = json.loads(path.read_text())
    if data.get("benchmark") != "refine_starts":
        raise SystemExit(f"error: {path} is not a starts file of this benchmark (--answers-out)")
    if (data["bundle"], data["first"], data["limit"]) != (a.bundle, a.first, a.limit):
        raise SystemExit(f"error: {path} answers {data['bundle']} targets {data['first']}+{data['limit']}, "
                         f"not {a.bundle} {a.first}+{a.limit}")
    return data["method"], {name: [np.asarray(t, dtype=np.float64) for t in s["starts"]]
                             for name, s in data["sets"].items()}


def _write_starts(answered: dict[str, Any], a: argparse.Namespace) -> None:
    import json

    sets = {name: {"starts": [[c.theta.tolist() for c in r.candidates] for r in results], "answer_s": dt}
            for name, (_, results, dt) in answered.items()}
    method = next((r.method for _, results, _ in answered.values() for r in results), a.method)
    a.answers_out.parent.mkdir(parents=True, exist_ok=True)
    a.answers_out.write_text(json.dumps({"benchmark": "refine_starts", "bundle": a.bundle, "method": method,
                                         "first": a.first, "limit": a.limit, "starts_per_target": a.starts,
                                         "seed": a.seed, "sets": sets}) + "\n")


def _refine_one(inv: Any, results: list[Any], strategy: str, a: argparse.Namespace, overrides: dict[str, Any],
                sim: Any, name: str = "") -> tuple[list[dict[str, Any]], float]:
    import copy

    from invphys.inverter.refine import refine

    opts = _machine().sim_options(a.strategy_option) if strategy == "corrected" else None
    t0 = time.perf_counter()
    records = refine(inv, copy.deepcopy(results), a.budget, a.popsize, a.sigma0, overrides=overrides,
                     batch_size=a.sim_batch, seed=a.seed, simulator=sim, extract_workers=a.extract_workers,
                     log=None if a.log_dir is None else a.log_dir / f"refine_{name}_{strategy}_{a.first}.npz",
                     extract_threads=a.extract_threads or None, ask_workers=a.ask_workers,
                     strategy=strategy, known_starts=a.known_starts, strategy_options=opts or None,
                     **({} if a.stop is None else {"stop": a.stop}),
                     **({} if a.patience is None else {"patience": a.patience}),
                     **({} if a.min_gain is None else {"min_gain": a.min_gain}), cost_budget=a.cost_budget)
    return records, time.perf_counter() - t0


def _write(result: dict[str, Any], out: Path | None) -> None:
    """The JSON so far (after every strategy), without printing it."""
    import json

    if out:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({**_machine().provenance(), **result}, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    if a.first < 0 or a.limit < 0 or a.extract_threads < 0 or a.ask_workers < 0:
        raise SystemExit("error: --first, --limit, --extract-threads and --ask-workers must be >= 0")
    if a.dataset_runs is not None and a.dataset_runs < 1:
        raise SystemExit("error: --dataset-runs must be >= 1")
    if a.min_gain is not None and a.patience is None:
        raise SystemExit("error: --min-gain needs --patience N")
    if a.log_dir is not None:
        a.log_dir.mkdir(parents=True, exist_ok=True)
    import invphys
    from invphys.core.interfaces import Simulator

    sets = _target_sets(a.targets)
    inv = invphys.load_inverter(a.bundle)
    answered = _answer_sets(inv, sets, a)
    if a.answers_out:
        _write_starts(answered, a)
        return 0
    overrides = _machine().sim_options(a.sim_option)
    sim = inv.simulator(overrides)
    ext = inv.extractor(sim)
    own = type(sim).simulate_feed is not Simulator.simulate_feed
    if own and not a.native_feed:
        use_default_feed(sim)
    feed = ("the simulator's own (an open stream)" if own and a.native_feed
            else "default (chunks of ready rows)")
    space = sim.parameter_space()
    rng = np.random.default_rng(a.seed + 1)
    pool = None
    if a.extract_workers:
        from invphys.plugins.executors._extract_pool import ExtractionPool

        pool = ExtractionPool(ext, a.extract_workers, threads=a.extract_threads or None)
    warm = _dataset(sim, ext, space.denormalize(rng.random((a.sim_batch, space.dim))), a.sim_batch, pool)  # compiles
    fed = _recording(sim)
    result: dict[str, Any] = {
        "what": "refine on the simulator vs dataset generation, same warm simulator and slots",
        "device": _machine().simulator_device(sim), "simulator": sim.name, "simulator_version": sim.version,
        "simulator_config": sim.config.model_dump(), "overrides": overrides, "feed": feed, "bundle": a.bundle,
        "method": a.method, "targets": a.targets[0] if len(a.targets) == 1 else sets, "sim_batch": a.sim_batch,
        "extract_workers": a.extract_workers, "extract_threads": a.extract_threads or None,
        "ask_workers": a.ask_workers, "first": a.first, "strategies": a.strategy, "budget": a.budget, "warmup": warm,
        "stop": a.stop, "patience": a.patience, "min_gain": a.min_gain, "cost_budget": a.cost_budget, "sets": {}}
    if a.answers_in:
        result["answers_in"] = str(a.answers_in)
    for n_set, (name, path) in enumerate(sets.items()):
        y, results, answer_s = answered[name]
        result["answer_s"] = result.get("answer_s", 0.0) + answer_s
        result["method"] = results[0].method if results else a.method   # the starts' own (an --answers-in file's)
        blocks: dict[str, dict[str, Any]] = {}
        entry = result["sets"][name] = {"path": path, "targets": len(y), "first": a.first, "strategies": blocks}
        for n_strat, strategy in enumerate(a.strategy):
            fed.clear()
            records, wall = _refine_one(inv, results, strategy, a, overrides, sim, name)
            blocks[strategy] = _strategy_block(records, wall, a.bootstrap)
            if n_set == 0 and n_strat == 0:   # the first refine: timed against dataset generation of its runs
                _first(result, blocks[strategy], records, a, sim, ext, np.array(fed), pool, rng)
            entry["paired"] = _paired(blocks, a.bootstrap)
            _write(result, a.out)
    if pool is not None:
        pool.close()
    _machine().emit(result, a.out)
    return 0


def _first(result: dict[str, Any], block: dict[str, Any], records: list[dict[str, Any]], a: argparse.Namespace,
           sim: Any, ext: Any, fed: np.ndarray, pool: Any, rng: np.random.Generator) -> None:
    """The first refine's timing against dataset generation of the very runs it simulated (same parameters,
    so the same cost per run), and its top-level record (the keys this benchmark always wrote)."""
    space = sim.parameter_space()
    ref = {"targets": len(records), "budget": a.budget, "starts": a.starts, "popsize": a.popsize,
           "sigma0": a.sigma0, "strategy": a.strategy[0],
           **{k: block[k] for k in ("runs", "wall_s", "s_per_run", "simulator_s")}, **_summary(records)}
    result.update({"dataset": None, "dataset_random": None, "refine": ref, "refine_over_dataset": None,
                   "per_target": [{k: v for k, v in r.items() if k not in ("call", "settings")} for r in records]})
    _write(result, a.out)   # the refine is kept if the dataset timing below is cut short
    if not len(fed):   # every run replayed from --log-dir: no runs of this process to time
        result["dataset"] = "not timed: every refine run was replayed from --log-dir"
    elif not a.skip_dataset:
        result["dataset"] = data = _dataset(sim, ext, fed[:a.dataset_runs], a.sim_batch, pool)
        result["refine_over_dataset"] = ref["s_per_run"] / data["s_per_run"]
    if a.random_dataset and len(fed):
        result["dataset_random"] = _dataset(sim, ext, space.denormalize(rng.random((len(fed), space.dim))),
                                            a.sim_batch, pool)


if __name__ == "__main__":
    raise SystemExit(main())
