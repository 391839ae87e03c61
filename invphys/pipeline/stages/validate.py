"""The ``validate`` stage: re-run recovered parameters through the real simulator (paper sec. 3.6).

Takes the invert stage's rows for the first ``targets.validate`` targets (and every named-objective
row), simulates their theta* in batches with the spec's ``validator`` (``simulator`` re-runs the
spec's simulator, with its ``overrides`` applied), and records per row: R_surr, R_actual, the gap
Delta = R_surr - R_actual, the actual features, the failure reason of a failed run and the run's
wall time. For objective rows R is the named objective's score instead of R_gt. Identical theta* are
simulated once.

With ``report.render`` on, the best-recovered run of the first ``RENDER_TARGETS`` targets is kept
(every time series whole, particle frames reduced to the last one), and so is the run of each such target's
ground-truth parameters (the noise floor's run of the same vector, else one simulated for the renders), so
that the report can draw target and recovered runs side by side and
plot their time series (``renders/tNN_target.npz``, ``tNN_recovered.npz``: framework trajectory files,
:mod:`invphys.core.trajectory_io`).
The evaluation protocol (``evaluation:`` in the spec, docs/evaluation.md) adds its own answers,
validated with the rest: the ``baselines`` (nearest-neighbour lookup, sbi's NPE; fitted on the
training partition, answering every target; cached in ``baselines.json``), the ``noise_floor`` (each
validated target's true parameters) and the ``methods`` (ask/tell CMA-ES refinements started at another
label's answer, scored on the simulator in the loop or on the uncertainty-penalised surrogate).
Their rows are written to ``evaluation_rows.json`` for the report.

Writes ``validation.json`` and ``validation.csv``.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from invphys.pipeline.artifacts import objectives, to_params
from invphys.pipeline.stage_files import (
    EVALUATION_ROWS_FILE,
    RENDER_TARGETS,
    VALIDATION_FILE,
    baselines,
    load_results,
    summarise,
)

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("simulator", "features", "validator", "targets", "evaluation")

SIMULATED_FILE = "simulated.jsonl"


@contextmanager
def _run_bar(ctx: StageContext, total: int, label: str) -> Iterator[Any]:
    """A progress bar over simulator runs; yields the ``on_run`` callback (None without progress)."""
    if not ctx.progress or total == 0:
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn(label), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=ctx.console, transient=False) as bar:
        task = bar.add_task(label, total=total)
        yield lambda _row: bar.advance(task)


def run(ctx: StageContext) -> dict[str, Any]:
    """Validate the invert stage's answers and the evaluation protocol's on the simulator (see the module
    docstring); writes ``validation.json``/``.csv`` and ``evaluation_rows.json``."""
    from invphys.core.atomic import write_json

    rows, targets = load_results(ctx)
    n_val = int(ctx.spec.targets.validate_n)
    validator = ctx.registry.create("validator", ctx.spec.validator)
    simulator, extractor = ctx.simulator(), ctx.extractor()
    ckpt = _checkpoint(ctx, validator, simulator, extractor)
    extra, eval_info = evaluation_rows(ctx, rows, targets, validator, simulator, extractor, ckpt)
    write_json(ctx.stage_dir / EVALUATION_ROWS_FILE, extra)
    chosen = [r for r in rows + extra if (r["problem"] == "target" and r["target_index"] < n_val)
              or r["problem"] == "objective"]
    if not chosen:
        write_json(ctx.stage_dir / VALIDATION_FILE, [])
        return {"validated": 0, "note": "nothing to validate (targets.validate is 0 and no objectives)",
                "evaluation": eval_info}
    theta = np.array([r["theta"] for r in chosen])
    unique, inverse = np.unique(np.round(theta, 12), axis=0, return_inverse=True)
    inverse = np.asarray(inverse).reshape(-1)
    render = bool(ctx.spec.report.render)
    ctx.log(f"simulating {len(unique)} recovered parameter vectors ({len(chosen)} rows) "
            f"with validator {validator.name!r}")
    done = _simulate_chosen(ctx, chosen, targets, theta, unique, inverse, validator, simulator, extractor, ckpt)
    out = _validation_rows(ctx, chosen, done)
    if ctx.spec.evaluation.best_of:
        from invphys.evaluation.answers import best_of_rows

        sel_a, sel_v = best_of_rows(ctx.spec.evaluation.best_of, rows + extra, out)
        extra += sel_a
        out += sel_v
        write_json(ctx.stage_dir / EVALUATION_ROWS_FILE, extra)
    renders = (_renders(ctx, chosen, out, inverse, done.sim, validator, simulator, extractor, targets)
               if render else [])
    write_json(ctx.stage_dir / VALIDATION_FILE, out)
    import pandas as pd

    pd.DataFrame([{k: v for k, v in r.items() if k not in ("theta", "actual")} for r in out]).to_csv(
        ctx.stage_dir / "validation.csv", index=False)
    failed = sum(1 for r in out if r["failure"])
    ctx.log(f"validated {len(out)} rows ({failed} failed runs)")
    return {"validated": len(out), "simulated": len(unique), "failed": failed, "renders": renders,
            "optimizers": summarise(out, "r_actual"), "evaluation": eval_info}


@dataclass
class _Validated:
    """The chosen rows' simulations: the validator's records of recovery rows (by row index) and, for a
    validator with ``simulate_features``, every row's features, failure and run stats (``sim``: the
    unique vectors' simulation)."""

    by_row: dict[int, Any]
    sim: Any = None
    feats: np.ndarray | None = None
    failures: list[Any] | None = None
    stats: list[Any] | None = None


def _simulate_chosen(ctx: StageContext, chosen: list[dict[str, Any]], targets: dict[str, Any], theta: np.ndarray,
                     unique: np.ndarray, inverse: np.ndarray, validator: Any, simulator: Any, extractor: Any,
                     ckpt: Any) -> _Validated:
    """Simulate each unique vector once (replaying the stage's memo) and score the recovery rows."""
    scales = np.asarray(targets["scales"])
    target_rows = [i for i, r in enumerate(chosen) if r["problem"] == "target"]
    if not hasattr(validator, "simulate_features"):  # a third-party validator: recovery targets only
        recs = validator.validate(theta[target_rows], _targets_of(chosen, target_rows, targets),
                                  _predicted(chosen, target_rows), simulator, extractor, scales) if target_rows else []
        return _Validated(by_row=dict(zip(target_rows, recs, strict=True)))
    # keep trajectories only of runs that may be rendered (the first RENDER_TARGETS targets)
    # (the noise floor's runs among them: they are the targets' own runs that the renders draw)
    render = bool(ctx.spec.report.render)
    keep = {int(inverse[i]) for i in target_rows if chosen[i]["target_index"] < RENDER_TARGETS} if render else False
    assert ckpt is not None
    reused0 = ckpt.reused  # the in-loop replay above counts too
    with _run_bar(ctx, len(unique), "validating") as on_run:
        sim = ckpt.simulate(unique, _bound(validator, simulator, extractor), validator.config.batch_size,
                            len(extractor.feature_names), keep_trajectories=keep, on_run=on_run)
    if ckpt.reused:
        ctx.log(f"{ckpt.reused - reused0} of {len(unique)} validated vectors ({ckpt.reused} simulator calls' "
                f"vectors in all) reused from {ckpt.path.name} (a resumed validation)")
    feats = sim.features[inverse]
    failures = [sim.failures[j] for j in inverse]
    stats = [sim.stats[j] for j in inverse]
    recs = []
    if target_rows:
        from invphys.plugins.validators.simulator import SimulatedFeatures

        sub = SimulatedFeatures(feats[target_rows], [failures[i] for i in target_rows],
                                [stats[i] for i in target_rows], [None] * len(target_rows))
        recs = validator.records(theta[target_rows], _targets_of(chosen, target_rows, targets),
                                 _predicted(chosen, target_rows), sub, scales)
    return _Validated(by_row=dict(zip(target_rows, recs, strict=True)), sim=sim, feats=feats, failures=failures,
                      stats=stats)


def _validation_rows(ctx: StageContext, chosen: list[dict[str, Any]], done: _Validated) -> list[dict[str, Any]]:
    """One validation row per chosen row that has a result: a recovery row's record, or a named
    objective's score on the surrogate's prediction and on the simulated features."""
    by_row, feats, failures, stats = done.by_row, done.feats, done.failures, done.stats
    named = objectives(ctx) if any(r["problem"] == "objective" for r in chosen) else {}
    out: list[dict[str, Any]] = []
    for i, r in enumerate(chosen):
        base = {k: r[k] for k in ("optimizer", "type", "space", "evaluator", "problem", "problem_id",
                                  "target_index", "dataset_row", "evaluations", "wall_time_s", "theta")}
        base.update({k: r[k] for k in ("role", "simulator_runs", "simulator_time_s", "device") if k in r})
        if i in by_row:
            rec = by_row[i]
            base.update(r_surrogate=rec.r_surrogate, r_actual=rec.r_actual, gap=rec.gap, failure=rec.failure,
                        actual=None if rec.actual is None else rec.actual.tolist(),
                        sim_time_s=None if rec.stats is None else rec.stats.wall_time_s)
        elif feats is not None and failures is not None and stats is not None and r["problem"] == "objective":
            obj = named[r["problem_id"]]
            ok = failures[i] is None
            r_surr = float(np.asarray(obj(np.asarray(r["predicted"])[None, :])).reshape(-1)[0])
            r_act = float(np.asarray(obj(feats[i][None, :])).reshape(-1)[0]) if ok else float("nan")
            base.update(r_surrogate=r_surr, r_actual=r_act, gap=r_surr - r_act, failure=failures[i],
                        actual=feats[i].tolist() if ok else None,
                        sim_time_s=None if stats[i] is None else stats[i].wall_time_s)
        else:
            continue
        out.append(base)
    return out


def _bound(validator: Any, simulator: Any, extractor: Any) -> Any:
    return lambda theta, **kw: validator.simulate_features(theta, simulator, extractor, **kw)


def _checkpoint(ctx: StageContext, validator: Any, simulator: Any, extractor: Any) -> Any:
    """The stage's crash-safe memo of simulated vectors (None for a validator without simulate_features)."""
    if not hasattr(validator, "simulate_features"):
        return None
    from invphys.core.dataset import RunIdentity, extractor_identity
    from invphys.pipeline.runner import fingerprint
    from invphys.pipeline.sim_checkpoint import SimCheckpoint

    # the runs' identity as a dataset store keys them (device and batching do not count) and the resolved
    # extractor's (not the spec's wording of it); memos keyed by the spec's features section still replay
    sim = validator.simulator_for(simulator) if hasattr(validator, "simulator_for") else simulator
    run = RunIdentity.of(sim).to_dict()
    identity = fingerprint({"run": run, "features": extractor_identity(extractor)})
    legacy = fingerprint({"run": run, **ctx.spec.section_dump(["features"])})
    return SimCheckpoint(ctx.stage_dir / SIMULATED_FILE, identity, legacy=[legacy])


def evaluation_rows(ctx: StageContext, rows: list[dict[str, Any]], targets: dict[str, Any], validator: Any,
                    simulator: Any, extractor: Any, ckpt: Any = None) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Baseline rows (every target), noise-floor and method rows (validated targets), and their metrics."""
    from invphys.evaluation.answers import noise_floor_rows, refine_rows
    from invphys.evaluators.simulator_loop import SimulatorEvaluator

    ev = ctx.spec.evaluation
    n_val = min(int(ctx.spec.targets.validate_n), len(targets["rows"]))
    extra, metrics = baselines(ctx, targets)
    info: dict[str, Any] = {"baselines": metrics}
    if n_val and ev.noise_floor and targets.get("theta") is None:
        ctx.log("noise floor skipped: the targets have no ground truth (targets.values / targets.file)")
    elif n_val and ev.noise_floor:
        extra += noise_floor_rows(list(range(n_val)), targets, np.asarray(targets["scales"]),
                                  ctx.surrogate().predict, to_params(ctx))
    answers = rows + extra
    for label, method in ev.methods.items():
        n = min(n_val, method.targets or n_val)
        starts = {r["target_index"]: np.asarray(r["theta"]) for r in answers
                  if r["optimizer"] == method.start and r["problem"] == "target" and r["target_index"] < n}
        if not starts:
            ctx.log(f"[yellow]warning:[/] evaluation.methods.{label}: {method.start!r} answered no validated target")
            continue
        sim_eval = None
        if method.evaluator == "simulator" and ckpt is not None:  # generations memoised: a resumed run replays them
            sim_eval = SimulatorEvaluator(lambda th: ckpt.simulate(th, _bound(validator, simulator, extractor), len(th),
                                                                   len(extractor.feature_names)))
        elif method.evaluator == "simulator":
            from invphys.core.errors import InvphysError

            raise InvphysError(f"evaluation.methods.{label}: the simulator in the loop needs a validator with "
                               f"simulate_features (the 'simulator' validator)")
        ctx.log(f"{label}: ask/tell CMA-ES from {method.start} on {len(starts)} targets, {method.budget} "
                f"{'simulator runs' if sim_eval else 'surrogate evaluations'} each")
        got = refine_rows(label, method, starts, targets, np.asarray(targets["scales"]), ctx.surrogate().predict,
                          to_params(ctx), seed=ctx.seed, surrogate=ctx.surrogate(), sim_evaluator=sim_eval)
        extra += got
        info[label] = {"targets": len(got), "mean_in_loop_score": float(np.mean([r["in_loop_score"] for r in got]))}
        if sim_eval is not None:
            info[label].update(simulator_runs=sim_eval.runs, batches=sim_eval.batches, failed=sim_eval.failed,
                               simulator_time_s=sim_eval.wall_time_s, device=sim_eval.device,
                               simulator_time_per_target_s=sim_eval.wall_time_s / len(got))
        ctx.log(f"{label}: mean in-loop score {info[label]['mean_in_loop_score']:.3f}")
    return extra, info


def _targets_of(chosen: list[dict[str, Any]], idx: list[int], targets: dict[str, Any]) -> np.ndarray:
    feats = np.asarray(targets["features"])
    return np.array([feats[chosen[i]["target_index"]] for i in idx])


def _predicted(chosen: list[dict[str, Any]], idx: list[int]) -> np.ndarray:
    return np.array([chosen[i]["predicted"] for i in idx])


def _save_frame(path: Any, traj: Any) -> None:
    """Keep a run's time series whole and its last particle frame (if any) in a trajectory file."""
    from invphys.core.trajectory_io import save_trajectory

    save_trajectory(traj.last_frame(), path)


def _renders(ctx: StageContext, chosen: list[dict[str, Any]], out: list[dict[str, Any]], inverse: np.ndarray, sim: Any,
             validator: Any, simulator: Any, extractor: Any, targets: dict[str, Any]) -> list[dict[str, Any]]:
    """Keep the last frames of target and best recovered runs for the first RENDER_TARGETS targets."""
    if sim is None or targets.get("theta") is None:  # no ground truth: nothing to draw the answers against
        return []
    d = ctx.stage_dir / "renders"
    d.mkdir(exist_ok=True)
    rendered = []
    ks = sorted({r["target_index"] for r in out if r["problem"] == "target"})[:RENDER_TARGETS]
    if not ks:
        return []
    truths = _truth_runs(ctx, chosen, inverse, sim, validator, simulator, extractor, targets, ks)
    for n, k in enumerate(ks):
        cands = [(i, r) for i, r in enumerate(chosen) if r["problem"] == "target" and r["target_index"] == k
                 and r.get("role") != "reference"]
        vals = {i: next((o["r_actual"] for o in out if o["problem"] == "target" and o["target_index"] == k
                         and o["optimizer"] == r["optimizer"]), float("nan")) for i, r in cands}
        finite = {i: v for i, v in vals.items() if np.isfinite(v)}
        if not finite:
            continue
        best = max(finite, key=lambda i: finite[i])
        traj = sim.trajectories[int(inverse[best])]
        if traj is None:  # simulated by an earlier (resumed) run: simulate it again for its frames
            traj = validator.simulate_features(np.asarray(chosen[best]["theta"])[None, :], simulator, extractor,
                                               keep_trajectories=True).trajectories[0]
        if traj is None or truths[n] is None:
            continue
        _save_frame(d / f"t{k:02d}_recovered.npz", traj)
        _save_frame(d / f"t{k:02d}_target.npz", truths[n])
        rendered.append({"target_index": k, "optimizer": chosen[best]["optimizer"], "r_actual": finite[best]})
    return rendered


def _truth_runs(ctx: StageContext, chosen: list[dict[str, Any]], inverse: np.ndarray, sim: Any, validator: Any,
                simulator: Any, extractor: Any, targets: dict[str, Any], ks: list[int]) -> list[Any]:
    """The trajectories of targets ``ks``' true parameters: the noise floor's runs where this call kept them
    (the same vectors: simulated once), else simulated now."""
    truths: list[Any] = [None] * len(ks)
    for n, k in enumerate(ks):
        i = next((i for i, r in enumerate(chosen) if r["optimizer"] == "noise_floor" and r["problem"] == "target"
                  and r["target_index"] == k), None)
        if i is not None and np.array_equal(chosen[i]["theta"], targets["theta"][k]):
            truths[n] = sim.trajectories[int(inverse[i])]
    todo = [n for n, t in enumerate(truths) if t is None]
    if todo:
        with _run_bar(ctx, len(todo), "simulating targets for renders") as on_run:
            got = validator.simulate_features(np.array([targets["theta"][ks[n]] for n in todo]), simulator,
                                              extractor, keep_trajectories=True, on_run=on_run)
        for n, t in zip(todo, got.trajectories, strict=True):
            truths[n] = t
    return truths
