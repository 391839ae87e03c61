"""Replay stop rules on a ``bench_refine.py`` result: what a stall stop would have given, from measured runs.

A refine's stop rules (``stop``: the best R_actual reached; ``patience``/``min_gain``: the best gained less
than ``min_gain`` over the last ``patience`` told runs) are decided before each of a target's generations
from its own told runs only, so a target stopped by a rule ran exactly the first runs of the same target
without it. Its best R_actual after each run (``best_r_by_run``) and the sizes of its told generations
(``batches``) are in the result's per-target records, so replaying a rule on them gives the answers that
rule would have given, without a simulator run. Records written before ``batches`` existed: the
generations are assumed to be the target's starts (``--starts``, default the result's own) then
``--popsize`` runs each, which the output says per set (then decision points are approximate); the
free starts' best (``best_r_free``, before any run) is taken as unknown (-inf) when not recorded.
A rule that would go on past a recorded target's last run (it stopped there under the measured rule)
cannot be replayed there: such targets are counted as ``cut_short`` (keep the grid's ``stop`` at or
below the measured one). Per set and rule: mean R_actual with a 95 % bootstrap interval over targets, the
mean runs, the lowest R, targets stalled / stopped, and the GPU-s per target projected as mean runs x the
set's measured wall seconds per run (a projection: the rule must be validated on the GPU). ``--cost-budget C
...`` also replays cost budgets (typical runs) on records that hold each run's estimated cost (``cost_by_run``:
a target stops at the last run whose cumulative cost fits, inside a generation too, as the refine does).
Example::

    python benchmarks/bench_refine_replay.py benchmarks/results/refine_paper_h200.json \\
        --out benchmarks/results/refine_replay_paper_h200.json

Reads the per-target lists of the result's ``sets.<set>.strategies.<strategy>.per_target``, and of its
``shards`` and ``earlier_*`` blocks (merged results); CPU only, seconds.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np


def bootstrap(v: np.ndarray, n: int = 2000, seed: int = 0) -> dict[str, float | None]:
    """Mean of ``v`` and its 95 % percentile bootstrap interval (resampling targets; seeded)."""
    v = np.asarray(v, float)
    if not len(v):
        return {"mean": None, "lo": None, "hi": None}
    means = v[np.random.default_rng(seed).integers(0, len(v), (n, len(v)))].mean(1)
    return {"mean": float(v.mean()), "lo": float(np.percentile(means, 2.5)), "hi": float(np.percentile(means, 97.5))}


def _sources(doc: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """The result itself, its shards and its ``earlier_*`` blocks (each may hold per-target lists)."""
    out = [("", doc)]
    out += [(f"shards.{k}", v) for k, v in (doc.get("shards") or {}).items() if isinstance(v, dict)]
    out += [(k, v) for k, v in doc.items() if k.startswith("earlier_") and isinstance(v, dict)]
    return out


def collect(doc: dict[str, Any], strategy: str | None = None) -> dict[str, list[tuple[dict[str, Any], dict[str, Any]]]]:
    """``{set: [(per-target record, the block it came from), ...]}`` for ``strategy`` (None: the result's
    ``strategy``, else each block's first)."""
    strategy = strategy or doc.get("strategy")
    sets: dict[str, list[tuple[dict[str, Any], dict[str, Any]]]] = {}
    for _, src in _sources(doc):
        for name, entry in (src.get("sets") or {}).items():
            blocks = entry.get("strategies") if isinstance(entry, dict) else None
            if not blocks:
                continue
            block = blocks.get(strategy) if strategy else next(iter(blocks.values()))
            if block and block.get("per_target"):
                sets.setdefault(name, []).extend((r, src) for r in block["per_target"])
    return sets


def batches_of(rec: dict[str, Any], starts: int, popsize: int) -> tuple[list[int], bool]:
    """The target's told generations' sizes (recorded: True; else assumed: ``starts``, then ``popsize``)."""
    runs = int(rec["runs"])
    if rec.get("batches"):
        return [int(b) for b in rec["batches"]], True
    out, n = [min(starts, runs)] if runs else [], min(starts, runs)
    while n < runs:
        out.append(min(popsize, runs - n))
        n += out[-1]
    return out, False


def replay(rec: dict[str, Any], batches: list[int], stop: float | None, patience: int, min_gain: float,
           cap: float | None = None) -> tuple[int, float, str]:
    """(runs, final best R, how it ended: ``stalled``, ``stopped``, ``capped`` (its runs' recorded costs,
    ``cost_by_run``, passed ``cap`` typical runs: the refine keeps the head of a generation that fits),
    ``ran`` (all its recorded runs) or ``cut_short`` (the rule would run past the record's last run, where the
    measured rule stopped it))."""
    best = [-np.inf if v is None else float(v) for v in rec.get("best_r_by_run") or []]
    free = rec.get("best_r_free")
    bests = [-np.inf if free is None else float(free), *best]
    n, why = _by_rule(bests, batches, bool(rec.get("stopped") or rec.get("stalled")), stop, patience, min_gain)
    if cap is not None:
        from invphys.evaluators.stream_refine import affordable

        k = affordable(0.0, np.asarray(rec["cost_by_run"], float), cap)   # the refine's own rule
        if k < n:
            return k, bests[k], "capped"
        if why == "ran" and rec.get("capped"):
            why = "cut_short"
    return n, bests[n], why


def _by_rule(bests: list[float], batches: list[int], ended: bool, stop: float | None, patience: int,
             min_gain: float) -> tuple[int, str]:
    """Where the stop and stall rules end a target whose best R after 0, 1, ... runs is ``bests``."""
    runs = len(bests) - 1
    n = batches[0] if batches else 0
    for size in [*batches[1:], 0]:
        if n > runs or (n == runs and not ended):   # no runs left: no decision
            break
        why = decide(bests[:n + 1], stop, patience, min_gain)
        if why:
            return n, why
        if n == runs:
            return n, "cut_short"
        n += size
    return runs, "ran"


def decide(bests: list[float], stop: float | None, patience: int, min_gain: float) -> str:
    """The refine's rules before a generation, from the best R after 0, 1, ..., n told runs: ``stopped``
    (the best reached ``stop``), ``stalled`` (n >= patience > 0 and best(n) - best(n - patience) < min_gain;
    no change, -inf to -inf included, is a gain of 0) or "" (go on)."""
    from invphys.evaluators.stream_refine import stalled

    if stop is not None and 0.0 < stop < 1.0 and bests[-1] >= stop:
        return "stopped"
    return "stalled" if stalled(bests, patience, min_gain) else ""


def rule_row(recs: list[dict[str, Any]], batches: list[list[int]], s_per_run: float | None, stop: float | None,
             patience: int, min_gain: float, n_boot: int, base: np.ndarray | None = None,
             cap: float | None = None) -> dict[str, Any]:
    """One rule on one set: mean R with its interval, mean runs, lowest R, ends, projected GPU-s per target."""
    out = [replay(r, b, stop, patience, min_gain, cap) for r, b in zip(recs, batches, strict=True)]
    r = np.array([v if np.isfinite(v) else 0.0 for _, v, _ in out])   # no successful run: 0, as bench_refine
    runs = np.array([n for n, _, _ in out], float)
    row = {"stop": stop, "patience": patience, "min_gain": min_gain if patience else None, "cost_budget": cap,
           "r": bootstrap(r, n_boot), "runs_per_target": float(runs.mean()) if len(runs) else None,
           "r_min": float(r.min()) if len(r) else None,
           **{k: sum(e == k for _, _, e in out) for k in ("stalled", "stopped", "capped", "cut_short")},
           "gpu_s_per_target": float(runs.mean() * s_per_run) if len(runs) and s_per_run else None}
    if base is not None:
        row["r_minus_measured"] = bootstrap(r - base, n_boot, seed=1)
    return row


def _s_per_run(doc: dict[str, Any], name: str, pairs: list[tuple[dict[str, Any], dict[str, Any]]]) -> float | None:
    """The set's measured wall seconds per run: the merged result's, else its blocks' wall over their runs."""
    top = (doc.get("sets") or {}).get(name) or {}
    if isinstance(top.get("s_per_run"), (int, float)):
        return float(top["s_per_run"])
    wall = runs = 0.0
    for src in {id(s): s for _, s in pairs}.values():
        for block in ((src.get("sets") or {}).get(name) or {}).get("strategies", {}).values():
            wall, runs = wall + float(block.get("wall_s") or 0.0), runs + float(block.get("runs") or 0.0)
            break
    return wall / runs if runs else None


def run(doc: dict[str, Any], stops: list[float | None], patiences: list[int], gains: list[float],
        strategy: str | None = None, starts: int | None = None, popsize: int | None = None,
        n_boot: int = 2000, caps: list[float] | None = None) -> dict[str, Any]:
    """Every rule of the grid on every set of ``doc`` (each with no cost budget, then each of ``caps`` where
    every target recorded its runs' costs)."""
    ref = doc.get("refine") or next((s.get("refine") for _, s in _sources(doc) if s.get("refine")), {}) or {}
    starts = starts or int(ref.get("starts") or 4)
    popsize = popsize or int(ref.get("popsize") or 8)
    out: dict[str, Any] = {}
    for name, pairs in collect(doc, strategy).items():
        recs = [r for r, _ in pairs]
        got = [batches_of(r, starts, popsize) for r in recs]
        batches, recorded = [b for b, _ in got], sum(k for _, k in got)
        spr = _s_per_run(doc, name, pairs)
        base = np.array([0.0 if r.get("r_actual") is None else float(r["r_actual"]) for r in recs])
        costed = all(len(r.get("cost_by_run") or []) == r["runs"] for r in recs)
        rules = [(s, 0, 0.0) for s in stops] + [(s, p, g) for s in stops for p in patiences if p for g in gains]
        rules = [(*rule, c) for c in [None, *(caps or [] if costed else [])] for rule in rules]
        out[name] = {
            "targets": len(recs), "s_per_run": spr, "measured": bootstrap(base, n_boot),
            "measured_runs_per_target": float(np.mean([r["runs"] for r in recs])),
            "batches": "recorded" if recorded == len(recs) else
            f"assumed for {len(recs) - recorded} of {len(recs)} targets (not recorded): their {starts} starts in "
            f"one generation, then generations of {popsize} (decision points approximate)",
            "best_r_free": "recorded" if all("best_r_free" in r for r in recs) else
            "not recorded for some targets: their free starts' best is taken as -inf (no stall decided against it)",
            "cost_by_run": "recorded" if costed else "not recorded for every target: no cost budget replayed",
            "rules": [rule_row(recs, batches, spr, s, p, g, n_boot, base, c) for s, p, g, c in rules]}
    return out


def _table(sets: dict[str, Any]) -> str:
    lines = ["| set | stop | patience | min gain | cost budget | mean R [95 % CI] | runs | min R | stalled | capped | "
             "GPU-s/target (projected) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in sets.items():
        for r in s["rules"]:
            ci, gpu = r["r"], r["gpu_s_per_target"]
            lines.append(f"| {name} | {r['stop']} | {r['patience'] or 'off'} | {r['min_gain'] or '-'} | "
                         f"{r['cost_budget'] or 'off'} | {ci['mean']:.3f} [{ci['lo']:.3f}, {ci['hi']:.3f}] | "
                         f"{r['runs_per_target']:.1f} | {r['r_min']:.3f} | {r['stalled']} | {r['capped']} | "
                         f"{'-' if gpu is None else f'{gpu:.1f}'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("result", type=Path, help="a bench_refine.py result JSON (per-target best_r_by_run)")
    p.add_argument("--stop", type=float, nargs="+", default=[0.98], help="stop R values (0: none)")
    p.add_argument("--patience", type=int, nargs="+", default=[8, 16, 24, 32], help="runs")
    p.add_argument("--min-gain", type=float, nargs="+", default=[0.002, 0.005, 0.01, 0.02])
    p.add_argument("--strategy", default=None, help="the strategy's records (default: the result's)")
    p.add_argument("--starts", type=int, default=None, help="starts per target when batches are not recorded")
    p.add_argument("--popsize", type=int, default=None, help="generation size when batches are not recorded")
    p.add_argument("--cost-budget", type=float, nargs="*", default=[],
                   help="cost budgets (typical runs) to replay too, where the records hold cost_by_run")
    p.add_argument("--bootstrap", type=int, default=2000)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    try:
        doc = json.loads(a.result.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"error: cannot read {a.result}: {exc}") from None
    if any(x < 0 for x in a.patience) or any(not 0 <= g <= 1 for g in a.min_gain) or any(not 0 <= s <= 1 for s in a.stop):
        raise SystemExit("error: --patience >= 0, --min-gain and --stop in [0, 1]")
    if any(not 0 < c <= 1e9 for c in a.cost_budget):
        raise SystemExit("error: --cost-budget values must be in (0, 1e9] typical runs")
    stops = [s if 0 < s < 1 else None for s in a.stop]
    sets = run(doc, stops, a.patience, a.min_gain, a.strategy, a.starts, a.popsize, a.bootstrap, a.cost_budget)
    if not sets:
        raise SystemExit(f"error: {a.result} holds no per-target records with best_r_by_run")
    result = {
        "script": "benchmarks/bench_refine_replay.py",
        "command": " ".join(["python", "benchmarks/bench_refine_replay.py", *map(shlex.quote, argv or sys.argv[1:])]),
        "device": f"none (CPU replay of runs measured on: {doc.get('device', 'unknown')})",
        "source": str(a.result),
        "note": "Replays measured simulator runs: each target's recorded best R_actual after each run under other "
                "stop rules. A rule decides before each generation from the target's own told runs, so a stopped "
                "target's runs are a prefix of the measured ones: the replayed answers are exact up to the "
                "decision points (exact where batches are recorded). GPU-s per target are projected (mean runs x "
                "the set's measured wall s per run), not measured: validate a rule on the GPU before it becomes a "
                "default.",
        "sets": sets}
    print(_table(sets))
    for name, s in sets.items():
        print(f"{name}: {s['targets']} targets, {s['s_per_run']} s per run; batches {s['batches']}; free starts' "
              f"best {s['best_r_free']}; costs {s['cost_by_run']}")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
