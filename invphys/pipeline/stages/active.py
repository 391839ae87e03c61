"""The ``active`` stage: active learning rounds on the targets (spec section ``active:``).

Round r (0 .. ``rounds``) for the first ``active.targets`` targets (default: the validated ones):

1. propose: CMA-ES (ask/tell, ``budget`` surrogate evaluations per target, optionally penalised by
   the ensemble's std) on the current surrogate, started at each target's best simulated answer so
   far (round 0: the ``start`` label's answer, e.g. the nearest-neighbour baseline);
2. simulate every proposal in one batch through the validator: this is round r's R_actual, and the
   best simulated answer per target so far is the ``active_learning`` method's answer after round r;
3. add the successfully simulated proposals to the training rows and retrain the surrogate (same
   plugin and config as the train stage; ``max_epochs`` caps it). The dataset store is not modified:
   the added rows are written to ``added.npz``.

Writes ``rounds.json`` (per round: training rows, the surrogate's R^2 on the test partition, mean
R_actual of the proposals and of the best-so-far answers with bootstrap intervals, simulator runs
and time), ``rows.json``/``validation.json`` (the final answers as report rows: label
``active_learning``) and ``surrogate_round<r>/`` (each retrained surrogate). The report shows the
rounds and treats ``active_learning`` like any method. Policies are not retrained.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from invphys.core.errors import InvphysError

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("simulator", "features", "validator", "surrogate", "targets", "evaluation", "active")

ROUNDS_FILE = "rounds.json"
LABEL = "active_learning"


def _starts(ctx: StageContext, label: str, ks: list[int], targets: dict[str, Any]) -> np.ndarray:
    from invphys.pipeline.stages.invert import load_results
    from invphys.pipeline.stages.validate import baselines, load_evaluation_rows

    rows, _ = load_results(ctx)
    pool = rows + load_evaluation_rows(ctx)
    if not any(r["optimizer"] == label for r in pool) and label in ctx.spec.evaluation.baselines:
        pool += baselines(ctx, targets)[0]
    by = {r["target_index"]: r["theta"] for r in pool if r["optimizer"] == label and r["problem"] == "target"}
    missing = [k for k in ks if k not in by]
    if missing:
        labels = sorted({r["optimizer"] for r in pool})
        raise InvphysError(f"active.start: {label!r} answered no target {missing[:5]} (labels with answers: "
                           f"{', '.join(labels) or 'none'})")
    return np.array([by[k] for k in ks], dtype=np.float64)


def _retrain(ctx: StageContext, theta: np.ndarray, y: np.ndarray) -> Any:
    block = dict(ctx.spec.surrogate or {})
    kind = block.pop("type")
    if ctx.spec.active is not None and ctx.spec.active.max_epochs:
        block["max_epochs"] = ctx.spec.active.max_epochs
    cls = ctx.registry.get("surrogate", kind)
    model = cls(cls.Config(**block))
    model.fit(theta, y)
    return model


def run(ctx: StageContext) -> dict[str, Any]:
    from invphys.core.atomic import write_json
    from invphys.core.objectives import recovery_reward
    from invphys.evaluation.stats import bootstrap_mean_ci
    from invphys.models.data import r2_scores
    from invphys.pipeline.stages.invert import load_results
    from invphys.pipeline.stages.validate import _to_params
    from invphys.plugins.evaluators.simulator_loop import SimulatorEvaluator, refine_targets
    from invphys.plugins.evaluators.uncertainty import UncertaintyPenalty

    sec = ctx.spec.active
    if sec is None:
        raise InvphysError("the active stage needs an 'active' section")
    _, targets = load_results(ctx)
    n = min(sec.targets or int(ctx.spec.targets.validate_n) or len(targets["rows"]), len(targets["rows"]))
    ks = list(range(n))
    feats = np.asarray(targets["features"], dtype=np.float64)[ks]
    scales = np.asarray(targets["scales"], dtype=np.float64)
    data = ctx.dataset()
    train_idx, test_idx = ctx.split()
    theta_tr, y_tr = data.theta[train_idx], data.y[train_idx]
    validator = ctx.registry.create("validator", ctx.spec.validator)
    if not hasattr(validator, "simulate_features"):
        raise InvphysError("the active stage simulates through a validator with simulate_features ('simulator')")
    sim = SimulatorEvaluator.from_validator(validator, ctx.simulator(), ctx.extractor())
    best_theta = _starts(ctx, sec.start, ks, targets)
    best_r = np.full(n, -np.inf)
    best_y = np.full_like(feats, np.nan)
    surrogate = ctx.surrogate()
    added_theta: list[np.ndarray] = []
    added_y: list[np.ndarray] = []
    rounds = []
    for r in range(sec.rounds + 1):
        t0 = time.perf_counter()
        pen = UncertaintyPenalty(surrogate, scales, sec.uncertainty_penalty)
        refined = refine_targets(feats, best_theta, scales, pen.predict, sec.budget, sec.popsize, sec.sigma0,
                                 seed=ctx.seed * 1000 + r,
                                 score=lambda y, t, pen=pen: recovery_reward(y, t, scales) - pen.penalty(y))
        proposals = np.array([x.theta for x in refined])
        propose_s = time.perf_counter() - t0
        runs0, sim_s0 = sim.runs, sim.wall_time_s
        y_sim = sim(proposals)
        ok = np.all(np.isfinite(y_sim), axis=1)
        r_act = np.where(ok, recovery_reward(np.where(ok[:, None], y_sim, 0.0), feats, scales), 0.0)
        better = r_act > best_r
        best_r = np.where(better, r_act, best_r)
        best_theta = np.where(better[:, None], proposals, best_theta)
        best_y = np.where(better[:, None], y_sim, best_y)
        r2 = float(r2_scores(data.y[test_idx], surrogate.predict(data.theta[test_idx]))[0]) if len(test_idx) > 1 else None
        m, lo, hi = bootstrap_mean_ci(r_act, ctx.spec.evaluation.bootstrap, ctx.spec.evaluation.confidence, ctx.seed)
        bm, blo, bhi = bootstrap_mean_ci(best_r, ctx.spec.evaluation.bootstrap, ctx.spec.evaluation.confidence,
                                         ctx.seed)
        rounds.append({"round": r, "train_rows": int(len(theta_tr) + sum(len(a) for a in added_theta)),
                       "surrogate_r2_test": r2, "r_actual_mean": m, "r_actual_ci95": [lo, hi],
                       "best_so_far_mean": bm, "best_so_far_ci95": [blo, bhi], "failed": int((~ok).sum()),
                       "simulator_runs": sim.runs - runs0, "simulator_s": sim.wall_time_s - sim_s0,
                       "propose_s": propose_s, "device": sim.device})
        ctx.log(f"round {r}: {rounds[-1]['train_rows']} training rows, surrogate R^2 {r2 if r2 is None else round(r2, 3)}, "
                f"R_actual {m:.3f} [{lo:.3f}, {hi:.3f}], best so far {bm:.3f}")
        if r == sec.rounds:
            break
        added_theta.append(proposals[ok])
        added_y.append(y_sim[ok])
        t1 = time.perf_counter()
        surrogate = _retrain(ctx, np.concatenate([theta_tr, *added_theta]), np.concatenate([y_tr, *added_y]))
        surrogate.save(ctx.stage_dir / f"surrogate_round{r + 1}")
        rounds[-1]["retrain_s"] = time.perf_counter() - t1
    write_json(ctx.stage_dir / ROUNDS_FILE, rounds)
    if added_theta:
        np.savez_compressed(ctx.stage_dir / "added.npz", theta=np.concatenate(added_theta), y=np.concatenate(added_y))
    to_params = _to_params(ctx)
    predicted = surrogate.predict(best_theta)
    runs_per_target = sim.runs / max(n, 1)
    rows, val = [], []
    for i, k in enumerate(ks):
        row = {"optimizer": LABEL, "type": "active_learning", "role": "method", "space": "raw", "evaluator": "shared",
               "problem": "target", "problem_id": f"t{k:02d}", "target_index": k, "dataset_row": targets["rows"][k],
               "r_surrogate": float(recovery_reward(predicted[i], feats[i], scales)),
               "evaluations": int(sec.budget * (sec.rounds + 1)), "counted_evaluations": int(sec.budget * (sec.rounds + 1)),
               "wall_time_s": float(sum(x["propose_s"] + x["simulator_s"] + x.get("retrain_s", 0.0) for x in rounds) / n),
               "theta": best_theta[i].tolist(), "point": best_theta[i].tolist(),
               "params": dict(zip(targets["param_names"], to_params(best_theta[i]), strict=True)),
               "predicted": predicted[i].tolist(), "history": [], "simulator_runs": runs_per_target,
               "device": sim.device or "cpu"}
        rows.append(row)
        finite = bool(np.isfinite(best_r[i]) and best_r[i] > -np.inf)
        val.append({**{key: row[key] for key in ("optimizer", "type", "role", "space", "evaluator", "problem", "problem_id",
                                                  "target_index", "dataset_row", "evaluations", "wall_time_s", "theta",
                                                  "simulator_runs", "device")},
                    "r_surrogate": row["r_surrogate"], "r_actual": float(best_r[i]) if finite else float("nan"),
                    "gap": row["r_surrogate"] - float(best_r[i]) if finite else float("nan"),
                    "failure": None if np.all(np.isfinite(best_y[i])) else "no proposal simulated successfully",
                    "actual": best_y[i].tolist() if np.all(np.isfinite(best_y[i])) else None, "sim_time_s": None})
    write_json(ctx.stage_dir / "rows.json", rows)
    write_json(ctx.stage_dir / "validation.json", val)
    return {"targets": n, "rounds": rounds, "simulator_runs": sim.runs}


def load_active(ctx: StageContext) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
    """(rows, validation rows, rounds) written by this stage, or empty lists when it has not run."""
    import json

    d = ctx.stage_dir_of("active")
    if not (d / "DONE.json").is_file():
        return [], [], []
    return (json.loads((d / "rows.json").read_text()), json.loads((d / "validation.json").read_text()),
            json.loads((d / ROUNDS_FILE).read_text()))
