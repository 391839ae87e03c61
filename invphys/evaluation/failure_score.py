"""Will this answer fail on the simulator? An answer-level failure score, fitted on validated answers.

The target-only OOD score (:mod:`invphys.evaluation.ood`) asks whether a target is unusual; this asks
whether its *answer* will reproduce it when simulated (R_actual >= 0.8). Scores of a target and its
answer (larger: more likely to fail), each a function of the two alone:

* ``knn``: the target's mean standardised distance to its 10 nearest training rows;
* ``misfit``: 1 - R_surr, the surrogate's own misfit of the answer to the target;
* ``local_error``: the surrogate's RMS normalised error, at their own parameters, on the 20 training
  rows nearest the target in standardised feature space (how well the surrogate knows that region;
  training rows identical to the target are left out, so a target that is itself a training row is
  scored as a new one).

A logistic regression on their logs (standardised), fitted on held-out answers re-simulated on the
simulator (``labels``: R_actual < 0.8), gives each answer a failure probability; the warning fires at or
above a threshold chosen on the same rows. The default rule (``alarms``) bounds false alarms: the threshold
is the quantile of the calibration rows' *typical* answers (those that reproduce their target) at which at
most ``ALARMS`` of them are warned, lowered by a margin of 1.5 standard errors of that rate on those rows, so
the warning fires on few typical targets and catches what stands out (distant targets, edges of the box).
The ``recall`` rule instead takes the largest threshold catching ``RECALL`` of the failing answers (it
fired on a third of typical answers for the paper bundle). The model is a handful of plain numbers
(:func:`fit` returns them as a JSON-ready dict, stored as ``failure`` in a bundle's diagnostics).
"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.evaluation.ood import K, auroc, feature_targets, knn_distance, neighbours, standardised_train

FORMAT = 1
SCORES: tuple[str, ...] = ("knn", "misfit", "local_error")
#: training rows whose surrogate error is averaged for ``local_error``
K_LOCAL = 20
#: an answer fails when its re-simulated R_actual is below this
FAIL_BELOW = 0.8
#: the share of failing calibration answers the warning must catch (the ``recall`` rule)
RECALL = 0.8
#: the share of typical calibration answers the warning may fire on (the default ``alarms`` rule)
ALARMS = 0.10
#: standard errors of that share taken off it, so a new set's alarm rate stays below ``ALARMS``
ALARM_MARGIN_SE = 1.5
#: L2 penalty of the logistic regression (on standardised scores; the intercept is not penalised)
PENALTY = 1.0
#: added before the log of each score (a misfit or distance of exactly 0 stays finite)
OFFSETS: dict[str, float] = {"knn": 1e-6, "misfit": 1e-3, "local_error": 1e-6}
_ERRORS: weakref.WeakKeyDictionary[Any, np.ndarray] = weakref.WeakKeyDictionary()


def _train_errors(bundle: Any) -> np.ndarray:
    """(N, M) the surrogate's normalised error at each finite training row's own parameters (cached)."""
    if bundle not in _ERRORS:
        theta, y = bundle.data("train")
        _, keep = standardised_train(bundle)
        mean = bundle.surrogate.predict(np.asarray(theta, dtype=np.float64)[keep])
        _ERRORS[bundle] = (np.asarray(mean, dtype=np.float64) - y[keep]) / bundle.scales
    return _ERRORS[bundle]


def local_error(bundle: Any, targets: Any, k: int = K_LOCAL) -> np.ndarray:
    """(B,) mean over the target's ``k`` nearest training rows (standardised given features, identical rows
    left out) of the surrogate's RMS normalised error there, over the features the target gives."""
    t = feature_targets(bundle, targets)
    _, idx = neighbours(bundle, t, k, leave_identical=True)
    err = _train_errors(bundle)[idx] ** 2  # (B, k, M)
    m = t.mask[:, None, :]
    rms = np.sqrt(np.sum(np.where(m, err, 0.0), axis=2) / np.maximum(m.sum(axis=2), 1))
    return rms.mean(axis=1)


def components(bundle: Any, targets: Any, answers: np.ndarray) -> dict[str, np.ndarray]:
    """Every score of :data:`SCORES` for targets (B, M) and their answers (B, d) in normalised units."""
    from invphys.core.masked_recovery import masked_recovery

    t = feature_targets(bundle, targets)
    theta = np.atleast_2d(np.asarray(answers, dtype=np.float64))
    if theta.shape != (len(t), bundle.space.dim):
        raise InvphysError(f"answers have shape {theta.shape}; expected ({len(t)}, {bundle.space.dim})")
    # one answer at a time: a batched network's float rounding would make a score depend on its batch
    mean = np.concatenate([np.asarray(bundle.surrogate.predict(theta[i:i + 1]), dtype=np.float64)
                           for i in range(len(theta))]) if len(theta) else np.zeros((0, len(t.feature_names)))
    r = masked_recovery(mean, np.nan_to_num(t.values), bundle.scales, t.mask, bundle.kappa)
    return {"knn": knn_distance(bundle, t, K, leave_identical=True), "misfit": 1.0 - r,
            "local_error": local_error(bundle, t)}


def _design(comps: dict[str, np.ndarray], names: list[str], offsets: dict[str, float]) -> np.ndarray:
    return np.column_stack([np.log(np.asarray(comps[n], dtype=np.float64) + float(offsets[n])) for n in names])


def _logistic(x: np.ndarray, y: np.ndarray, penalty: float = PENALTY, steps: int = 100) -> tuple[np.ndarray, float]:
    """(coefficients, intercept) of an L2-penalised logistic regression by Newton's method (deterministic)."""
    a = np.column_stack([np.ones(len(x)), x])
    w = np.zeros(a.shape[1])
    reg = np.full(a.shape[1], float(penalty))
    reg[0] = 0.0
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-(a @ w)))
        grad = a.T @ (p - y) + reg * w
        hess = (a * (p * (1 - p))[:, None]).T @ a + np.diag(reg) + 1e-9 * np.eye(a.shape[1])
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.max(np.abs(step)) < 1e-10:
            break
    return w[1:], float(w[0])


def probability(model: dict[str, Any], comps: dict[str, np.ndarray]) -> np.ndarray:
    """(B,) the model's failure probability of each answer from its :func:`components`."""
    names = list(model["scores"])
    x = (_design(comps, names, model["offsets"]) - np.asarray(model["mean"])) / np.asarray(model["std"])
    return 1.0 / (1.0 + np.exp(-(x @ np.asarray(model["coef"]) + float(model["intercept"]))))


def fit(comps: dict[str, np.ndarray], failed: np.ndarray, recall: float = RECALL,
        names: tuple[str, ...] = SCORES, rule: str = "alarms", alarms: float = ALARMS) -> dict[str, Any]:
    """The failure model (plain numbers) fitted on calibration answers: ``comps`` their components,
    ``failed`` whether each failed on the simulator; the threshold by ``rule`` (:func:`threshold`)."""
    failed = np.asarray(failed, dtype=bool)
    if failed.sum() < 5 or (~failed).sum() < 5:
        raise InvphysError(f"fitting a failure warning needs >= 5 failing and >= 5 other answers; got "
                           f"{int(failed.sum())} and {int((~failed).sum())}")
    offsets = {n: OFFSETS[n] for n in names}
    x = _design(comps, list(names), offsets)
    mean, std = x.mean(axis=0), x.std(axis=0)
    std = np.where(std > 0, std, 1.0)
    coef, intercept = _logistic((x - mean) / std, failed.astype(np.float64))
    model = {"format": FORMAT, "scores": list(names), "offsets": offsets, "transform": "log(score + offset)",
             "mean": mean.tolist(), "std": std.tolist(), "coef": coef.tolist(), "intercept": intercept,
             "fail_below": FAIL_BELOW, "k": K, "k_local": K_LOCAL}
    p = probability(model, comps)
    model["threshold"], model["threshold_rule"] = threshold(p, failed, rule, recall, alarms)
    model["calibration"] = measure(p, failed, model["threshold"])
    model["calibration"]["auroc_each"] = {n: auroc(comps[n], failed) for n in names}
    return model


def threshold(p: np.ndarray, failed: np.ndarray, rule: str = "alarms", recall: float = RECALL,
              alarms: float = ALARMS) -> tuple[float, dict[str, Any]]:
    """(the warning's threshold on failure probabilities ``p``, the rule as plain numbers). ``alarms``: the
    smallest threshold firing on at most ``alarms - 1.5 SE`` of the typical (not failing) answers;
    ``recall``: the largest threshold catching at least ``recall`` of the failing answers."""
    if rule == "recall":
        ranked = np.sort(p[failed])[::-1]
        return float(ranked[int(np.ceil(recall * len(ranked))) - 1]), {"rule": "recall", "recall": float(recall)}
    if rule != "alarms":
        raise InvphysError(f"unknown failure-threshold rule {rule!r} (alarms or recall)")
    typical = np.sort(p[~failed])
    n = len(typical)
    allowed = max(alarms - ALARM_MARGIN_SE * np.sqrt(alarms * (1 - alarms) / n), 0.0)
    k = int(np.floor(allowed * n))  # at most k typical answers at or above the threshold
    thr = float(np.nextafter(typical[n - k - 1], np.inf)) if k < n else float(typical[0])
    return thr, {"rule": "alarms", "alarms": float(alarms), "margin_se": ALARM_MARGIN_SE, "allowed": float(allowed)}


def measure(p: np.ndarray, failed: np.ndarray, threshold: float) -> dict[str, Any]:
    """Recall on failing answers, alarm rate on the others, AUROC, counts."""
    failed = np.asarray(failed, dtype=bool)
    fires = np.asarray(p) >= threshold
    return {"n": len(failed), "failing": int(failed.sum()), "warned": int(fires.sum()),
            "recall": float(fires[failed].mean()) if failed.any() else None,
            "alarm_rate": float(fires[~failed].mean()) if (~failed).any() else None,
            "auroc": auroc(np.asarray(p), failed)}


def validated_answers(path: Any, method: str, sets: tuple[str, ...] | None = None) -> dict[str, dict[str, Any]]:
    """Per set: ``y`` (N, M) targets, ``theta`` (N, d) the ``method``'s answers (normalised), ``failed``
    (R_actual < 0.8), ``keys`` and ``truth_theta`` (or None), from a per-target file of validated answers
    (``benchmarks/bench_user_targets.py --validate --per-target-out``)."""
    from invphys.core.safe_read import UserFileError, load_user_json

    try:
        data = load_user_json(path, what="validated answers")
    except UserFileError as exc:
        raise InvphysError(str(exc)) from exc
    if not isinstance(data, dict) or not isinstance(data.get("sets"), dict) or not data.get("validated"):
        raise InvphysError(f"{path}: not a per-target file of validated answers (bench_user_targets.py "
                           f"--validate --per-target-out)")
    out = {}
    for name, block in data["sets"].items():
        if sets and name not in sets:
            continue
        m = (block.get("methods") or {}).get(method)
        if not isinstance(m, dict) or m.get("r_actual") is None:
            raise InvphysError(f"{path}: set {name!r} has no validated answers of method {method!r}")
        try:
            r = np.asarray(m["r_actual"], dtype=np.float64)
            out[name] = {"y": np.asarray(block["y"], dtype=np.float64), "theta": np.asarray(m["theta"], dtype=np.float64),
                         "failed": ~(r >= FAIL_BELOW), "keys": list(block.get("keys") or []),
                         "truth_theta": None if block.get("truth_theta") is None
                         else np.asarray(block["truth_theta"], dtype=np.float64)}
        except (KeyError, TypeError, ValueError) as exc:
            raise InvphysError(f"{path}: set {name!r} is malformed ({exc})") from exc
    missing = set(sets or ()) - set(out)
    if missing or not out:
        raise InvphysError(f"{path}: no set named {', '.join(sorted(missing)) or 'any'} (it holds "
                           f"{', '.join(data['sets'])})")
    return out


def training_rows(bundle: Any, truth_theta: np.ndarray | None) -> np.ndarray:
    """(N,) whether each row's true parameters are a training row's (None: unknown, all False)."""
    if truth_theta is None:
        return np.zeros(0, dtype=bool)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(np.asarray(bundle.data("train")[0], dtype=np.float64)).query(truth_theta)
    return np.asarray(d < 1e-9)


def fit_from_file(bundle: Any, failures: Any, method: str, keep_training: bool = False, rule: str = "alarms"
                  ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(the failure model, the components it was fitted on) from validated answers ``failures`` (``FILE`` or
    ``FILE:SET[,SET]``): rows whose true parameters are training rows of the bundle are left out unless
    ``keep_training`` (they are not held out), and counted in the model's ``rows``."""
    from pathlib import Path

    spec = str(failures)
    path, names = (spec, "") if Path(spec).exists() or ":" not in spec else spec.rsplit(":", 1)
    sets = validated_answers(path, method, tuple(names.split(",")) if names else None)
    y = np.concatenate([s["y"] for s in sets.values()])
    theta = np.concatenate([s["theta"] for s in sets.values()])
    failed = np.concatenate([s["failed"] for s in sets.values()])
    train = np.concatenate([training_rows(bundle, s["truth_theta"]) if s["truth_theta"] is not None
                            else np.zeros(len(s["y"]), dtype=bool) for s in sets.values()])
    use = np.ones(len(y), dtype=bool) if keep_training else ~train
    comps = components(bundle, y[use], theta[use])
    model = fit(comps, failed[use], rule=rule)
    model.update(method=method, rows={"file": Path(path).name, "sets": list(sets), "given": len(y),
                                      "training_rows": int(train.sum()), "training_rows_used": bool(keep_training),
                                      "used": int(use.sum())})
    return model, {**comps, "failed": failed[use]}
