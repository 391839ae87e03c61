"""Re-running answers through the bundle's simulator: validation and the simulator-in-the-loop polish.

:meth:`Inverter.validate <invphys.inverter.Inverter.validate>` and :meth:`Inverter.polish
<invphys.inverter.Inverter.polish>` call these; see their docstrings for the behaviour.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.counts import is_count
from invphys.core.errors import InvphysError
from invphys.core.masked_recovery import masked_recovery
from invphys.inverter.result import Candidate, InversionResult
from invphys.inverter.settings import PolishSettings

_LOG = logging.getLogger("invphys.inverter")


def simulation(inv: Any, overrides: Mapping[str, Any] | None, batch_size: int, extract_workers: int = 0
               ) -> tuple[Any, Any, Any]:
    """(simulator, extractor, simulator validator) for re-running candidates (``extract_workers``: feature
    extraction in that many processes while the simulator goes on; 0: in its thread)."""
    for name, v, low in (("batch_size", batch_size, 1), ("extract_workers", extract_workers, 0)):
        if not is_count(v, low):
            raise InvphysError(f"{name} must be >= {low}, got {v!r}")
    sim = inv.simulator(overrides)
    ext = inv.extractor(sim)
    return sim, ext, inv.bundle.registry.create("validator", {"type": "simulator", "batch_size": int(batch_size),
                                                              "extract_workers": int(extract_workers)})


def simulate(inv: Any, cands: list[tuple[InversionResult, Candidate]], sim: Any, ext: Any, validator: Any,
             on_run: Callable[[int], None] | None = None) -> None:
    """Simulate candidates (with their results): fills ``actual``, ``r_actual``, ``gap``, ``failure``."""
    if not cands:
        return
    b = inv.bundle
    theta = np.array([c.theta for _, c in cands])
    if hasattr(validator, "simulate_features"):
        sim_out = validator.simulate_features(theta, sim, ext, on_run=on_run)
        actual, failures = sim_out.features, sim_out.failures
    else:
        recs = validator.validate(theta, np.array([np.where(r.mask, r.target, 0.0) for r, _ in cands]),
                                  np.array([c.predicted for _, c in cands]), sim, ext, b.scales)
        actual = np.array([np.full(len(b.feature_names), np.nan) if x.actual is None else x.actual for x in recs])
        failures = [x.failure for x in recs]
    for j, (r, c) in enumerate(cands):
        c.failure = failures[j]
        if failures[j] is None:
            c.actual = np.asarray(actual[j], dtype=np.float64)
            c.r_actual = float(masked_recovery(c.actual, r.target, b.scales, r.mask, b.kappa))
        else:
            c.actual, c.r_actual = None, float("nan")
        c.gap = c.r_surrogate - c.r_actual


def masked_score(inv: Any) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """R over each row's given features (a missing feature is NaN in ``targets``), as validation scores."""
    def score(y: np.ndarray, targets: np.ndarray) -> np.ndarray:
        given = np.isfinite(targets)
        return masked_recovery(y, np.where(given, targets, 0.0), inv.bundle.scales, given, inv.bundle.kappa)
    return score


#: how polish searches are seeded (in the log's key: a log of the older position-seeded searches is told apart)
POLISH_SEEDING = "per-target-1"


def polish_key(inv: Any, targets: np.ndarray, theta: np.ndarray, chosen: np.ndarray, settings: dict[str, Any],
               overrides: Mapping[str, Any] | None, legacy: bool = False) -> str:
    """What a polish log was made for: bundle, simulator config, targets, starts, settings (not the
    budget: a larger budget replays the smaller one's batches) and the seeding (``legacy``: the key the
    same polish had when searches were seeded by position)."""
    m = inv.bundle.manifest
    head = {"bundle": m.get("bundle_id", ""), "files": m.get("files", {}), "simulator": m["simulator"].get("config", {}),
            "overrides": dict(overrides or {}), "settings": {k: v for k, v in settings.items() if k != "budget"},
            "polished": chosen.tolist()}
    if not legacy:
        head["seeding"] = POLISH_SEEDING
    h = hashlib.sha256(json.dumps(head, sort_keys=True, default=str).encode())
    h.update(np.ascontiguousarray(targets, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(theta, dtype=np.float64).tobytes())
    return h.hexdigest()[:24]


def polish_seeds(items: list[InversionResult], ps: PolishSettings, seed: int) -> list[int]:
    """Each target's polish seed: from the user's seed, the target's values and mask and the search
    settings (:func:`~invphys.inverter.seeds.target_seed`), never from its place in the file."""
    from invphys.inverter.seeds import target_seed

    stream = f"{ps.popsize}/{ps.sigma0!r}"
    return [target_seed(seed, "polish", r.target, r.mask, stream) for r in items]


def _best_simulated(r: InversionResult) -> Candidate:
    return max(r.candidates, key=lambda c: -np.inf if c.r_actual is None or not np.isfinite(c.r_actual) else c.r_actual)


def polish(inv: Any, items: list[InversionResult], ps: PolishSettings, overrides: Mapping[str, Any] | None,
           batch_size: int, log: str | Path | None, seed: int, on_batch: Callable[[int, bool], None] | None) -> None:
    """:meth:`Inverter.polish` on ``items`` (updated in place)."""
    from invphys.evaluators.polish import BatchLog, Polished, check_polish_log
    from invphys.evaluators.polish import confirm as confirm_answers
    from invphys.evaluators.polish import polish as run_polish
    from invphys.evaluators.simulator_loop import SimulatorEvaluator

    if log is not None:
        check_polish_log(log)  # before anything is simulated
    sim, ext, validator = simulation(inv, overrides, batch_size)
    simulate(inv, [(r, c) for r in items for c in r.candidates if c.r_actual is None and c.failure is None],
             sim, ext, validator)
    starts = [_best_simulated(r) for r in items]
    m = len(inv.feature_names)
    targets = np.array([np.where(r.mask, r.target, np.nan) for r in items], dtype=np.float64)
    theta = np.array([c.theta for c in starts], dtype=np.float64)
    r0 = np.array([np.nan if c.r_actual is None else c.r_actual for c in starts], dtype=np.float64)
    feats = np.array([np.full(m, np.nan) if c.actual is None else c.actual for c in starts], dtype=np.float64)
    chosen = ~(r0 >= ps.below)  # NaN (the start failed) is polished too
    settings: dict[str, Any] = {"budget": ps.budget, "popsize": ps.popsize, "sigma0": ps.sigma0, "below": ps.below,
                                "seed": seed}
    key = polish_key(inv, targets, theta, chosen, settings, overrides)  # not confirm: a log without it replays
    old = polish_key(inv, targets, theta, chosen, settings, overrides, legacy=True)
    if ps.confirm:
        settings.update(confirm=ps.confirm, confirm_candidates=ps.confirm_candidates)
    batches = BatchLog(None if log is None else Path(log), key, SimulatorEvaluator.from_validator(validator, sim, ext),
                       log=_polish_note, chunk=batch_size, on_batch=on_batch, legacy_keys=(old,))
    t0 = time.perf_counter()
    if ps.budget > 0 and chosen.any():
        pol = run_polish(targets, theta, r0, feats, inv.bundle.scales, batches, ps.budget, ps.popsize, ps.sigma0,
                         ps.below, seed=seed, score=masked_score(inv), seeds=polish_seeds(items, ps, seed))
    else:
        pol = Polished(theta, r0, feats, np.zeros(len(items), np.int64), chosen & (ps.budget > 0), 0.0, 0, 0, "")
    polished_theta = pol.theta.copy()
    if ps.confirm:
        pol = confirm_answers(pol, targets, inv.bundle.scales, batches, ps.confirm, ps.confirm_candidates,
                              score=masked_score(inv)).apply(pol)
    total = int(pol.runs.sum())
    call = {"targets": len(items), "polished": int(chosen.sum()) if ps.budget > 0 else 0, "runs": total,
            "replayed_runs": batches.replayed_runs, "simulator_s": pol.seconds, "device": pol.device,
            "wall_time_s": time.perf_counter() - t0, "log": None if log is None else str(log)}
    for i, (r, start) in enumerate(zip(items, starts, strict=True)):
        improved = _apply(inv, r, start, i, pol, chosen[i] and ps.budget > 0, bool(ps.confirm), r0[i])
        r.polish = {"polished": bool(chosen[i] and ps.budget > 0), "improved": improved,
                    "start_source": start.source, "start_r_actual": float(r0[i]), "r_actual": float(pol.r_actual[i]),
                    "runs": int(pol.runs[i]), "simulator_s": float(pol.runs[i] / max(total, 1) * pol.seconds),
                    "device": pol.device, "settings": dict(settings), "call": call}
        if pol.confirmed is not None:
            r.polish["confirm"] = {**pol.confirmed.record(i), "selected_theta": [float(v) for v in polished_theta[i]]}


def _apply(inv: Any, r: InversionResult, start: Candidate, i: int, pol: Any, polished: bool, confirm: bool,
           r0: float) -> bool:
    """Put target ``i``'s polished (or confirmed) answer first (never worse than its start, the best simulated
    candidate, which leads also where nothing was polished); True when a new point became the answer."""
    new_theta, new_r, new_feats = pol.theta[i], pol.r_actual[i], pol.features[i]
    if confirm:  # the answer is a confirmed candidate: the start, or a point the polish simulated
        moved = bool((pol.confirmed is not None and pol.confirmed.pick[i] >= 0) or polished)
        improved = bool(moved and not np.array_equal(new_theta, start.theta))
    else:  # the answer is the best simulated point: the polished one, else the start (polished or not)
        moved = True
        improved = bool(polished and np.isfinite(new_r) and not new_r <= r0)
    if improved:
        cand = inv._calibrate_error_bars(inv._candidates(new_theta[None, :], [f"{start.source} + polish"], r.target,
                                                         r.mask))[0]
        cand.actual, cand.r_actual = new_feats.copy(), float(new_r)
        cand.gap = cand.r_surrogate - cand.r_actual
        r.candidates.insert(0, cand)
    elif moved:
        r.candidates.insert(0, r.candidates.pop(next(j for j, c in enumerate(r.candidates) if c is start)))
        if confirm:
            start.r_actual = float(new_r)
            start.gap = start.r_surrogate - start.r_actual
    return improved


def _polish_note(message: str) -> None:
    """The polish log's messages: each batch at debug level, anything unexpected at info."""
    quiet = message.startswith("polish batch") and "other points" not in message
    (_LOG.debug if quiet else _LOG.info)(message)
