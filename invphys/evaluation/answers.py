"""Answers the evaluation adds to an experiment's own: baselines, refinements and the noise floor.

Every function returns rows in the invert stage's row format (``optimizer``, ``type``, ``problem``,
``problem_id``, ``target_index``, ``dataset_row``, ``r_surrogate``, ``evaluations``, ``wall_time_s``,
``theta``, ``params``, ``predicted``, ...) plus ``role`` (``baseline``, ``method`` or ``reference``),
``simulator_runs`` and ``device``, so that validation and the report treat them like any optimiser's.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from invphys.core.objectives import recovery_reward


def _row(label: str, kind: str, role: str, k: int, targets: dict[str, Any], theta: np.ndarray,
         predicted: np.ndarray, scales: np.ndarray, to_params: Callable[[np.ndarray], list[float]],
         evaluations: int, wall: float, **extra: Any) -> dict[str, Any]:
    theta = np.clip(np.asarray(theta, dtype=np.float64), 0.0, 1.0)
    y_t = np.asarray(targets["features"][k], dtype=np.float64)
    r = float(recovery_reward(np.asarray(predicted, dtype=np.float64), y_t, scales))
    return {"optimizer": label, "type": kind, "role": role, "space": "raw", "evaluator": extra.pop("evaluator", "shared"),
            "problem": "target", "problem_id": f"t{k:02d}", "target_index": k, "dataset_row": targets["rows"][k],
            "r_surrogate": r, "evaluations": int(evaluations), "counted_evaluations": int(evaluations),
            "wall_time_s": float(wall), "theta": theta.tolist(), "point": theta.tolist(),
            "params": dict(zip(targets["param_names"], to_params(theta), strict=True)),
            "predicted": np.asarray(predicted, dtype=np.float64).tolist(), "history": [],
            "simulator_runs": int(extra.pop("simulator_runs", 0)), "device": extra.pop("device", "cpu"), **extra}


def baseline_rows(plugins: dict[str, Any], theta_train: np.ndarray, y_train: np.ndarray, scales: np.ndarray,
                  targets: dict[str, Any], predict_theta: Callable[[np.ndarray], np.ndarray],
                  to_params: Callable[[np.ndarray], list[float]], progress: bool = False,
                  log: Callable[[str], None] = print,
                  surrogate: Any = None) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Fit each baseline plugin on the training rows and answer every target.

    Baselines whose ``fit_key()`` agree share one fit. A baseline whose library is missing (npe
    without sbi) is skipped with a logged warning and listed under ``metrics[label]["skipped"]``.
    A baseline with ``uncertainty_penalty`` > 0 chooses among its candidates by R minus lambda x the
    ``surrogate``'s normalised std (an ensemble's ``predict_with_uncertainty``).
    Returns (rows, metrics per label).
    """
    from invphys.core.errors import InvphysError
    from invphys.plugins.baselines import answer_with_penalty

    feats = np.asarray(targets["features"], dtype=np.float64)
    rows: list[dict[str, Any]] = []
    metrics: dict[str, Any] = {}
    fitted: dict[str, Any] = {}
    for label, plugin in plugins.items():
        key = plugin.fit_key() if hasattr(plugin, "fit_key") else None
        try:
            if key is not None and key in fitted:
                plugin.adopt(fitted[key])
            else:
                plugin.fit(theta_train, y_train, scales, progress=progress)
                if key is not None:
                    fitted[key] = plugin
        except InvphysError as exc:
            if getattr(plugin, "extra", "") and "pip install" in str(exc):
                log(f"[yellow]warning:[/] baseline {label!r} skipped: {exc}")
                metrics[label] = {"skipped": str(exc)}
                continue
            raise
        ans = answer_with_penalty(plugin, feats, predict_theta, surrogate, scales, f"evaluation.baselines.{label}")
        predicted = np.asarray(predict_theta(ans.theta), dtype=np.float64)
        per = ans.wall_time_s / max(len(feats), 1)
        for k in range(len(feats)):
            rows.append(_row(label, plugin.name, "baseline", k, targets, ans.theta[k], predicted[k], scales,
                             to_params, int(ans.evaluations[k]), per,
                             evaluator="dataset" if plugin.name == "nearest_neighbour" else "posterior",
                             spread=None if not np.all(np.isfinite(ans.spread[k])) else ans.spread[k].tolist()))
        metrics[label] = {**plugin.metrics, "answer_time_s": ans.wall_time_s,
                          **{k: v for k, v in ans.info.items() if k in ("leakage", "answer", "samples", "uncertainty_penalty")}}
        log(f"baseline {label}: mean R_surr {np.mean([r['r_surrogate'] for r in rows if r['optimizer'] == label]):.3f}"
            f" ({ans.wall_time_s * 1e3 / max(len(feats), 1):.2f} ms per target)")
    return rows, metrics


def noise_floor_rows(ks: list[int], targets: dict[str, Any], scales: np.ndarray,
                     predict_theta: Callable[[np.ndarray], np.ndarray],
                     to_params: Callable[[np.ndarray], list[float]]) -> list[dict[str, Any]]:
    """The targets' own true parameters (label ``noise_floor``); R_surr is the surrogate's score of the truth."""
    if not ks:
        return []
    theta = np.asarray(targets["theta"], dtype=np.float64)[ks]
    predicted = np.asarray(predict_theta(theta), dtype=np.float64)
    return [_row("noise_floor", "ground_truth", "reference", k, targets, theta[i], predicted[i], scales, to_params,
                 0, 0.0, evaluator="none") for i, k in enumerate(ks)]


def refine_rows(label: str, method: Any, starts: dict[int, np.ndarray], targets: dict[str, Any],
                scales: np.ndarray, predict_theta: Callable[[np.ndarray], np.ndarray],
                to_params: Callable[[np.ndarray], list[float]], seed: int = 0, surrogate: Any = None,
                sim_evaluator: Any = None) -> list[dict[str, Any]]:
    """One evaluation ``method`` (spec ``evaluation.methods.<label>``) on the targets in ``starts``.

    ``evaluator: simulator`` scores populations with ``sim_evaluator`` (a
    :class:`~invphys.evaluators.simulator_loop.SimulatorEvaluator`), every target's generation
    in one batch; ``surrogate`` scores them on the surrogate, minus ``uncertainty_penalty`` times the
    ensemble's normalised std. Rows report the plain R_surr of the answer.
    """
    from invphys.evaluators.simulator_loop import refine_targets
    from invphys.evaluators.uncertainty import UncertaintyPenalty

    ks = sorted(starts)
    if not ks:
        return []
    feats = np.asarray(targets["features"], dtype=np.float64)[ks]
    x0 = np.array([starts[k] for k in ks])
    t0 = time.perf_counter()
    if method.evaluator == "simulator":
        wall0 = sim_evaluator.wall_time_s
        refined = refine_targets(feats, x0, scales, sim_evaluator, method.budget, method.popsize, method.sigma0, seed)
        device = sim_evaluator.device or "cpu"
        sim_wall = (sim_evaluator.wall_time_s - wall0) / len(ks)
        evals = 0
    else:
        pen = UncertaintyPenalty(surrogate, scales, method.uncertainty_penalty)
        refined = refine_targets(feats, x0, scales, pen.predict, method.budget, method.popsize, method.sigma0, seed,
                                 score=lambda y, t: recovery_reward(y, t, scales) - pen.penalty(y))
        device, sim_wall, evals = "cpu", None, None
    wall = (time.perf_counter() - t0) / len(ks)
    theta = np.array([r.theta for r in refined])
    predicted = np.asarray(predict_theta(theta), dtype=np.float64)
    rows = []
    for i, (k, r) in enumerate(zip(ks, refined, strict=True)):
        row = _row(label, f"cma_es+{method.evaluator}", "method", k, targets, r.theta, predicted[i], scales, to_params,
                   r.evaluated if evals is None else evals, wall, evaluator=method.evaluator,
                   simulator_runs=r.evaluated if method.evaluator == "simulator" else 0, device=device,
                   start=method.start, in_loop_score=r.score)
        row["history"] = [[int(e), float(s)] for e, s in r.history]
        if sim_wall is not None:
            row["simulator_time_s"] = sim_wall
        rows.append(row)
    return rows


def best_of_rows(best_of: dict[str, list[str]], answers: list[dict[str, Any]], validated: list[dict[str, Any]]
                 ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Simulator-selected answers (spec ``evaluation.best_of``): per target, the candidate with the highest R_actual.

    Only targets on which every candidate was validated get one. Its cost is the candidates' together:
    their evaluations and wall time summed, one simulator run per distinct candidate vector (plus any
    runs the candidates spent themselves). Returns (answer rows, validated rows), labelled ``label``.
    """
    ans = {(r["optimizer"], r["target_index"]): r for r in answers if r["problem"] == "target"}
    val = {(r["optimizer"], r["target_index"]): r for r in validated if r["problem"] == "target"}
    out_a, out_v = [], []
    for label, cands in best_of.items():
        ks = sorted({k for (lab, k) in val if lab in cands})
        for k in ks:
            if not all((c, k) in val and (c, k) in ans for c in cands):
                continue
            scores = [val[(c, k)]["r_actual"] for c in cands]
            finite = [(s, c) for s, c in zip(scores, cands, strict=True) if s is not None and np.isfinite(s)]
            if not finite:
                continue
            best = max(finite, key=lambda t: t[0])[1]
            distinct = {tuple(np.round(ans[(c, k)]["theta"], 12)) for c in cands}
            cost = {"optimizer": label, "type": "best_of", "role": "method", "source": best, "candidates": list(cands),
                    "evaluator": "simulator", "device": ans[(best, k)].get("device", "cpu"),
                    "evaluations": int(sum(ans[(c, k)]["evaluations"] for c in cands)),
                    "wall_time_s": float(sum(ans[(c, k)]["wall_time_s"] for c in cands)),
                    "simulator_runs": len(distinct) + int(sum(ans[(c, k)].get("simulator_runs", 0) for c in cands))}
            out_a.append({**ans[(best, k)], **cost, "counted_evaluations": cost["evaluations"]})
            out_v.append({**val[(best, k)], **cost})
    return out_a, out_v
