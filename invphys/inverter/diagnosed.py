"""What a bundle's diagnostics (``invphys diagnose BUNDLE --write``) change in its answers.

With ``diagnostics/calibration.json`` in the bundle: posterior draws (and so intervals and ``samples``) are
quantile-recalibrated per parameter, the surrogate's ``± std`` is scaled so that ±1.645 of it holds 90 % of
held-out errors, and a target whose out-of-distribution score exceeds the threshold calibrated on held-out rows
gets a warning. Without it, answers are the posterior's and the ensemble's own, as before.
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
    from invphys.evaluation.calibration import recalibrated_samples

    diag = diagnostics(bundle)
    out = recalibrated_samples(np.asarray(draws, dtype=np.float64)[None], diag)[0]
    block = ((diag or {}).get("posterior") or {}).get("recalibration") or {}
    return out, any(m is not None for m in block.get("maps") or [])


def feature_std(bundle: Any, std: np.ndarray) -> np.ndarray:
    """The ensemble's std (N, M) scaled to its calibrated error bars (unchanged without diagnostics)."""
    diag = diagnostics(bundle)
    if diag is None:
        return std
    from invphys.evaluation.surrogate_errors import calibrated_feature_std

    return calibrated_feature_std(std, diag, bundle.feature_names)


def ood_warning(bundle: Any, values: np.ndarray, mask: np.ndarray) -> list[str]:
    """A warning for a target farther from the training data than the calibrated threshold (none without
    diagnostics, or for a score that needs more than the target)."""
    diag = diagnostics(bundle)
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
