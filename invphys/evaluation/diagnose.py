"""``invphys diagnose``: calibration, out-of-distribution and surrogate error-bar checks of one bundle.

On rows the bundle never trained on (:mod:`~invphys.evaluation.heldout`, picked by key), split in two
by key: the *fit* half fits the OOD score's choice and threshold and the surrogate's error-bar factors,
the *check* half measures them. The posterior's recalibration is checked both ways (fitted on the fit
half and checked on the check half, and the other direction): a parameter is recalibrated only when
its correction helps out of fold, averaged over both (:mod:`~invphys.evaluation.recalibration_folds`), and the
block stored for answers is then fitted on all held-out rows. The two directions are reported side by
side, never pooled: two folds pooled cancel each other's errors and look better calibrated than
either is. The result is
``report`` (everything measured) and ``calibration`` (the numbers answers use, stored as
``diagnostics/calibration.json`` in a bundle). Given validated answers (``failures``: held-out targets
whose default answers were re-simulated), it also fits the answer-level failure warning
(:mod:`~invphys.evaluation.failure_score`); without them a stored one of the same bundle is kept.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.evaluation import calibration as cal
from invphys.evaluation import recalibration_folds as rf
from invphys.evaluation.heldout import HeldOut, heldout_rows
from invphys.evaluation.ood import NEEDS, SCORES, auroc, score_components
from invphys.evaluation.surrogate_errors import error_bar_coverage, fit_error_scales

_LOG = logging.getLogger("invphys.diagnose")
FORMAT = 1
#: a parameter is "not identified" when its mean central 90 % interval spans more than this share of its range
IDENTIFIED_WIDTH = 0.5
#: a held-out answer "fails" when its RMS normalised error over the identified parameters exceeds this
FAILURE_ERROR = 0.15
#: ... or (the second label) when its R_surr is below this
FAILURE_R = 0.8
#: the OOD threshold: this quantile of the fit rows' scores (the warning fires on ~8 % of typical rows,
#: leaving room for sampling noise under the 10 % allowed)
OOD_QUANTILE = 0.92
#: the failure label that picks the OOD score: the answer does not reproduce the target's features
#: (R_surr < FAILURE_R, or for an answer that is a stored row its real R), the held-out stand-in for
#: R_actual < 0.8; ``misfit`` (1 - R_surr) is that label itself, so it cannot be picked by it
CHOOSE_BY = "r_surr"
#: which parameters are recalibrated (:mod:`~invphys.evaluation.recalibration_folds`)
RECALIBRATION_RULE = ("a parameter is recalibrated (quantile map + location shift) only when its coverage error "
                      "(mean |coverage - level| over 50/80/90/95 %) out of fold, averaged over the two directions "
                      "(fitted on the fit half and checked on the check half, and the other way), is lower with the "
                      "correction than without; else its posterior is left as it is")


@dataclass
class Diagnosis:
    report: dict[str, Any]
    calibration: dict[str, Any]
    figures: dict[str, Any] = field(default_factory=dict)
    #: keys of the held-out rows it used (``diagnostics/rows_used.json``)
    keys: list[str] | None = None


def posterior_draws(inverter: Any, y: np.ndarray, n: int, seed: int, method: str | None = None) -> Any:
    """The bundle's posterior draws of complete targets ``y`` (the inverter's public draws API)."""
    return inverter.posterior(np.asarray(y, dtype=np.float64), n=n, seed=seed, method=method,
                              recalibrate=False)  # the posterior's own draws: what is measured


def _draws_in_chunks(inverter: Any, y: np.ndarray, n: int, seed: int, method: str | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(samples (N, n, d), outside_fraction (N,), clipped (N,) draws clipped to the box because too few
    fell inside); each target's draws are its own (chunks only log progress)."""
    samples, outside, clipped = [], [], []
    t0 = time.perf_counter()
    for i in range(0, len(y), 100):
        d = posterior_draws(inverter, y[i:i + 100], n, seed, method)
        samples.append(d.samples)
        outside.append(np.asarray(d.outside_fraction, dtype=np.float64))
        clipped.append(np.asarray(getattr(d, "clipped", np.zeros(len(d.samples))), dtype=np.float64))
        _LOG.info("posterior draws: %d/%d targets (%.0f s)", min(i + 100, len(y)), len(y), time.perf_counter() - t0)
    return np.concatenate(samples), np.concatenate(outside), np.concatenate(clipped)


def calibration_block(draws: np.ndarray, theta: np.ndarray, seed: int) -> dict[str, Any]:
    """Coverage per parameter, TARP and SBC of ``draws`` against ``theta``."""
    return {"n_rows": len(theta), "coverage": cal.central_coverage(draws, theta, seed=seed),
            "tarp": cal.tarp(draws, theta, seed=seed), "sbc": cal.sbc(draws, theta)}


def _recalibration(samples: np.ndarray, theta: np.ndarray, fit: np.ndarray, names: list[str], seed: int
                   ) -> tuple[dict[str, Any], dict[str, Any], np.ndarray]:
    """(the stored block, the report's blocks, the check rows' corrected draws): per parameter, the
    two-fold acceptance rule (:mod:`~invphys.evaluation.recalibration_folds`) on the fit/check halves
    decides whether it is recalibrated; the stored block is fitted on all held-out rows for those
    parameters. ``check_after`` / ``swapped`` are out of fold: each half corrected by the (masked) block
    its other half fitted."""
    folds = rf.two_fold(samples, theta, fit)
    keep = folds["keep"]
    block = cal.fit_posterior_recalibration(samples, theta, keep)
    fixed = cal.apply_posterior_recalibration(samples[~fit], rf.masked(folds["blocks"]["a_to_b"], keep))
    swapped = cal.apply_posterior_recalibration(samples[fit], rf.masked(folds["blocks"]["b_to_a"], keep))
    report = {"recalibrated": [n for n, k in zip(names, keep, strict=True) if k],
              "recalibration": {"rule": RECALIBRATION_RULE, "fitted_on": f"all {len(theta)} held-out rows",
                                "parameters": rf.evidence(folds, names)},
              "check_after": calibration_block(fixed, theta[~fit], seed),
              "swapped": {"note": "the other direction: the block fitted on the check half (same parameters), "
                                  "checked on the fit half (not pooled with check_after: two folds pooled cancel "
                                  "each other's errors)",
                          "before": calibration_block(samples[fit], theta[fit], seed),
                          "after": calibration_block(swapped, theta[fit], seed)}}
    return block, report, fixed


def _verdicts(after: dict[str, Any], names: list[str]) -> list[dict[str, Any]]:
    """Parameters whose SBC ranks stay non-uniform (p < 0.01) after recalibration, with their bias."""
    out = []
    for j, n in enumerate(names):
        p, bias = after["sbc"]["ks_pvalue"][j], after["sbc"]["bias"][j]
        if p < 0.01:
            out.append({"parameter": n, "ks_pvalue": p, "bias": bias,
                        "reading": "the truth sits above the posterior's median too often (posterior biased low)"
                        if bias > 0 else "the truth sits below the posterior's median too often (posterior biased high)"})
    return out


def _surrogate(bundle: Any, held: HeldOut, fit: np.ndarray) -> dict[str, Any]:
    mean, std = bundle.surrogate.predict_with_uncertainty(held.theta)
    if not np.any(std > 0):
        return {"available": False, "note": "the surrogate is a single network: no spread to scale"}
    scales = fit_error_scales(mean[fit], std[fit], held.y[fit])
    chk = ~fit
    return {"available": True, "scales": scales.tolist(), "n_fit": int(fit.sum()), "n_check": int(chk.sum()),
            "check_before": error_bar_coverage(mean[chk], std[chk], held.y[chk]),
            "check_after": error_bar_coverage(mean[chk], std[chk], held.y[chk], scales)}


def _answers(inverter: Any, y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The default method's answers in one batch and, per answer that is a stored row (a pool with
    ``exact``), its real R against the target (NaN for the others); None when it has no batched answer."""
    from invphys.inverter.pool import POOL_METHOD

    try:
        if inverter.bundle.methods.get(inverter.default_method, {}).get("type") == POOL_METHOD:
            results = inverter.invert_many(y, draws=1)
            known = [np.nan if r.r_known is None else r.r_known for r in results]
            return np.array([r.theta for r in results]), np.asarray(known, dtype=np.float64)
        theta = np.asarray(inverter.invert_array(y), dtype=np.float64)
        return theta, np.full(len(theta), np.nan)
    except InvphysError:
        return None


def _ood(inverter: Any, held: HeldOut, draws: Any, identified: np.ndarray, fit: np.ndarray
         ) -> tuple[dict[str, Any], dict[str, Any]]:
    """AUROC of every candidate score for failing default answers; the best one (on the fit half) kept.
    Without batched answers only ``knn`` is scored (its threshold still calibrated on the fit half)."""
    answered = _answers(inverter, held.y)
    answers = None if answered is None else answered[0]
    scores = score_components(inverter.bundle, held.y, answers, draws, SCORES)
    report: dict[str, Any] = {"candidates": {}, "chosen": "knn", "default_answer": {"method": inverter.default_method}}
    labels: dict[str, np.ndarray] = {}
    if answers is not None:
        cols = identified if identified.any() else np.ones(held.theta.shape[1], dtype=bool)
        err = np.sqrt(np.mean((answers[:, cols] - held.theta[:, cols]) ** 2, axis=1))
        r_surr = 1.0 - scores["misfit"]
        known = answered[1]  # an answer that is a stored row: its real R, not the surrogate's
        reproduced = np.where(np.isfinite(known), known, r_surr)
        labels = {"parameter_error": err > FAILURE_ERROR, "r_surr": reproduced < FAILURE_R}
        table = {name: {lab: {"fit": auroc(sc[fit], f[fit]), "check": auroc(sc[~fit], f[~fit])}
                        for lab, f in labels.items()} for name, sc in scores.items()}
        usable = [n for n in scores if n != "misfit" and not NEEDS.get(n)]  # what the warning computes from a target
        best = max(usable, key=lambda n: np.nan_to_num(table[n][CHOOSE_BY]["fit"], nan=0.0), default="knn")
        report.update(candidates=table, chosen=best,
                      failure={"parameter_error_above": FAILURE_ERROR, "over": "identified parameters",
                               "r_surr_below": FAILURE_R, "stored_rows_by_real_r": int(np.isfinite(known).sum()),
                               "rate_check": {k: float(v[~fit].mean()) for k, v in labels.items()},
                               "failing_check": {k: int(v[~fit].sum()) for k, v in labels.items()}},
                      chosen_by=f"AUROC on the fit rows for the {CHOOSE_BY!r} failures, among the scores the "
                                f"warning computes from the target alone ({', '.join(usable)}); the others are "
                                f"reported only", note="misfit is 1 - R_surr: its AUROC on the r_surr label is that label")
        report["default_answer"].update(mean_r_surr=float(r_surr.mean()), mean_r_reproduced=float(reproduced.mean()),
                                        mean_error_identified=float(err.mean()))
    else:
        report["note"] = "the default method has no batched answer: only knn is scored, no AUROC measured"
    best = report["chosen"]
    thr = float(np.quantile(scores[best][fit], OOD_QUANTILE))
    fires = scores[best][~fit] > thr
    report.update(threshold=thr, check={"fire_rate": float(fires.mean()),
                                        **{f"recall_{k}": _share(fires, v[~fit]) for k, v in labels.items()}})
    return report, {"score": best, "threshold": thr, "quantile": OOD_QUANTILE, "k": 10}


def _share(fires: np.ndarray, failed: np.ndarray) -> float | None:
    """Share of the failing rows the warning fires on (None without failures)."""
    return float(fires[failed].mean()) if failed.any() else None


@dataclass
class _Draws:
    samples: np.ndarray
    outside_fraction: np.ndarray


def _posterior(inverter: Any, held: HeldOut, fit: np.ndarray, draws: int, seed: int, method: str | None
               ) -> tuple[dict[str, Any], dict[str, Any] | None, Any, dict[str, Any]]:
    """(report blocks, calibration block, draws, figures) of the bundle's posterior (empty without one)."""
    try:
        label = inverter.posterior_method(method)
    except InvphysError as exc:
        if method:
            raise
        return {"posterior_method": None, "note": str(exc)}, None, None, {}
    names = list(inverter.bundle.space.names)
    samples, outside, clipped = _draws_in_chunks(inverter, held.y, draws, seed, label)
    before_all = calibration_block(samples, held.theta, seed)
    recal, rblocks, fixed = _recalibration(samples, held.theta, fit, names, seed)
    after = rblocks["check_after"]
    width90 = np.asarray(before_all["coverage"]["0.9"]["width"])
    blocks = {"posterior_method": label, "draws_per_row": int(draws),
              "outside_box": {"mean_outside_fraction": float(outside.mean()),
                              "clipped_share": float(clipped.sum() / (draws * len(clipped))),
                              "rows_with_clipping": int((clipped > 0).sum()),
                              "note": "outside: share of raw posterior draws outside the parameter box (rejected); "
                                      "clipped: share of the draws kept that had to be clipped into it (too few "
                                      "raw draws fell inside)"},
              "identified": {"max_width90": IDENTIFIED_WIDTH, "width90": width90.tolist(),
                             "not_identified": [n for n, w in zip(names, width90, strict=True) if w >= IDENTIFIED_WIDTH]},
              "all_rows": before_all, "check_before": calibration_block(samples[~fit], held.theta[~fit], seed),
              **rblocks, "after_recalibration_not_uniform": _verdicts(after, names)}
    calib = {"method": label, "parameters": names, "recalibration": recal}
    figures = {"ranks_before": cal.ranks(samples[~fit], held.theta[~fit]), "ranks_after": cal.ranks(fixed, held.theta[~fit])}
    return blocks, calib, _Draws(samples, outside), figures


def _failure(inverter: Any, failures: Any, keep_training: bool = False) -> dict[str, Any] | None:
    """The answer-level failure model: fitted on the validated answers ``failures`` (``FILE`` or
    ``FILE:SET[,SET]``; rows whose true parameters are training rows are left out unless
    ``keep_training``), else the bundle's stored one when it was fitted for this bundle, else None."""
    from invphys.evaluation import failure_score as fs

    bundle = inverter.bundle
    if failures is None:
        from invphys.evaluation.ood import load_diagnostics

        try:
            old = load_diagnostics(bundle) or {}
        except InvphysError as exc:  # unreadable diagnostics: this run replaces them, with no model to keep
            _LOG.warning("%s", exc)
            old = {}
        kept = old.get("failure")
        if kept and old.get("bundle_id") == bundle.manifest.get("bundle_id"):
            return {**kept, "kept": "from the bundle's previous diagnostics (no --failures given)"}
        return None
    return fs.fit_from_file(bundle, failures, inverter.default_method, keep_training)[0]


def diagnose(inverter: Any, stores: Any = None, rows: int | None = None, draws: int = 1000, seed: int = 0,
             method: str | None = None, failures: Any = None, keep_training: bool = False) -> Diagnosis:
    """Measure ``inverter``'s bundle on its held-out rows (at most ``rows``, the first by key); with
    ``failures`` (validated answers, see :func:`_failure`) fit its answer-level failure warning."""
    bundle = inverter.bundle
    held = heldout_rows(bundle, stores)
    if rows is not None:
        held = held.take(np.arange(min(int(rows), len(held))))
    if len(held) < 20:
        raise InvphysError(f"bundle {bundle.root}: only {len(held)} held-out rows found; diagnose needs >= 20 "
                           f"(point --data at the dataset stores of its simulator)")
    failure = _failure(inverter, failures, keep_training)  # first: a bad file stops it before the long part
    fit = held.split() == 0
    blocks, post_calib, samples, figures = _posterior(inverter, held, fit, draws, seed, method)
    width90 = np.asarray((blocks.get("identified") or {}).get("width90", [0.0] * bundle.space.dim))
    ood_report, ood_cal = _ood(inverter, held, samples, width90 < IDENTIFIED_WIDTH, fit)
    sur = _surrogate(bundle, held, fit)
    report = {
        "format": FORMAT, "bundle": str(bundle.root), "bundle_id": bundle.manifest.get("bundle_id"),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "seed": int(seed),
        "parameters": list(bundle.space.names), "features": list(bundle.feature_names), "levels": list(cal.LEVELS),
        "heldout": {**held.info, "rows_used": len(held), "fit_rows": int(fit.sum()), "check_rows": int((~fit).sum()),
                    "split": "by key: the last 8 hex digits of each row's key, even -> fit, odd -> check"},
        **blocks, "ood": ood_report, "surrogate_error_bars": sur, "failure": failure}
    calib: dict[str, Any] = {"format": FORMAT, "bundle_id": bundle.manifest.get("bundle_id"),
                             "created_utc": report["created_utc"], "ood": ood_cal}
    if post_calib is not None:
        calib.update(posterior=post_calib, identified=blocks["identified"])
    if sur.get("available"):
        calib["surrogate_error_scales"] = {"features": list(bundle.feature_names), "scales": sur["scales"],
                                           "z": 1.6448536269514722, "nominal": 0.9}
    if failure is not None:
        calib["failure"] = failure
    return Diagnosis(_plain(report), _plain(calib), figures, [str(k) for k in held.keys])


def _plain(obj: Any) -> Any:
    """JSON-safe copy: NumPy scalars to Python, NaN and infinities to None (strict JSON has neither)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj
