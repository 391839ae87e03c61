"""What a bundle's diagnostics (``invphys diagnose BUNDLE --write``) change in its answers.

With ``diagnostics/calibration.json`` in the bundle: posterior draws (and so intervals and ``samples``) are
quantile-recalibrated per parameter, the surrogate's ``± std`` is scaled so that ±1.645 of it holds 90 % of
held-out errors, and an answer whose failure score (:mod:`invphys.evaluation.failure_score`, fitted on validated
held-out answers) reaches its threshold gets a warning (without a failure model: a target whose
out-of-distribution score exceeds the threshold calibrated on held-out rows). Without diagnostics, answers
are the posterior's and the ensemble's own, as before.
"""

from __future__ import annotations

from typing import Any

import numpy as np

_MISSING = object()
DIAGNOSTICS = "diagnostics/calibration.json"


def diagnostics(bundle: Any) -> dict[str, Any] | None:
    """The bundle's stored diagnostics (read once per loaded bundle), or None."""
    cached = bundle._cache.get("diagnostics", _MISSING)
    if cached is _MISSING:
        from invphys.evaluation.ood import load_diagnostics

        if (bundle.root / DIAGNOSTICS).exists():  # inside the bundle and covered by its checksums
            bundle.part(DIAGNOSTICS, "the bundle's diagnostics")
        cached = bundle._cache["diagnostics"] = load_diagnostics(bundle)
    return cached


def recalibrated(bundle: Any, draws: np.ndarray) -> tuple[np.ndarray, bool]:
    """(draws (S, d) corrected by the stored recalibration, whether a correction applied)."""
    from invphys.evaluation.calibration import has_recalibration, recalibrated_samples

    diag = diagnostics(bundle)
    out = recalibrated_samples(np.asarray(draws, dtype=np.float64)[None], diag)[0]
    return out, has_recalibration(diag)


def feature_std(bundle: Any, std: np.ndarray) -> np.ndarray:
    """The ensemble's std (N, M) scaled to its calibrated error bars (unchanged without diagnostics)."""
    diag = diagnostics(bundle)
    if diag is None:
        return std
    from invphys.evaluation.surrogate_errors import calibrated_feature_std

    return calibrated_feature_std(std, diag, bundle.feature_names)


def failure_score(bundle: Any, values: np.ndarray, mask: np.ndarray, theta: np.ndarray) -> float | None:
    """The stored failure model's probability that this answer fails on the simulator (R_actual < 0.8),
    from the target (``values`` over ``mask``) and the answer ``theta`` (normalised) alone; None where
    the bundle holds no failure model (``invphys diagnose --write --failures``)."""
    model = (diagnostics(bundle) or {}).get("failure")
    if not model:
        return None
    from invphys.evaluation.failure_score import components, probability

    given = {n: float(v) for n, v, m in zip(bundle.feature_names, values, mask, strict=True) if m}
    comps = components(bundle, given, np.asarray(theta, dtype=np.float64)[None])
    return float(probability(model, comps)[0])


def ood_warning(bundle: Any, values: np.ndarray, mask: np.ndarray, theta: np.ndarray | None = None,
                score: float | None = None) -> list[str]:
    """A warning for an answer likely to fail on the simulator (with ``theta`` and a stored failure model;
    ``score``: its :func:`failure_score` when already computed), else for a target farther from the training
    data than the calibrated threshold (none without diagnostics, or for a score that needs more than the
    target)."""
    diag = diagnostics(bundle)
    if theta is not None and (diag or {}).get("failure"):
        return failure_warning(bundle, values, mask, theta, score)
    from invphys.evaluation.ood import NEEDS, ood_score, ood_settings

    settings = ood_settings(diag)
    if diag is None or settings["threshold"] is None or NEEDS.get(settings["score"]):
        return []
    given = {n: float(v) for n, v, m in zip(bundle.feature_names, values, mask, strict=True) if m}
    score = float(ood_score(bundle, given, diagnostics=diag)[0])
    threshold = float(settings["threshold"])
    if score <= threshold:
        return []
    return [f"unusual target: farther from the training data than the held-out rows the warning was calibrated on "
            f"({settings['score']} score {score:.3g} > {threshold:.3g}); its answer and intervals are less reliable"]


def failure_warning(bundle: Any, values: np.ndarray, mask: np.ndarray, theta: np.ndarray,
                    score: float | None = None) -> list[str]:
    """The answer-level warning: its failure score (``score``, or computed here) at or above the stored
    threshold."""
    model = (diagnostics(bundle) or {})["failure"]
    p = failure_score(bundle, values, mask, theta) if score is None else score
    if p is None or p < float(model["threshold"]):
        return []
    cal = model.get("calibration") or {}
    held = (f"; on {cal['n']} validated held-out answers the warning caught {cal['recall']:.0%} of those that failed "
            f"and fired on {cal['alarm_rate']:.0%} of the others") if cal.get("recall") is not None else ""
    return [f"this answer may not reproduce the target on the simulator: failure score {p:.2f} >= {model['threshold']:.2f}"
            f", the estimated probability that its simulated R is below {model.get('fail_below', 0.8):g}{held}; "
            f"validate it (--validate) before relying on it"]
