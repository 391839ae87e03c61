"""Adaptive design: spend a simulation budget where a surrogate is unsure (``dataset.adaptive``).

A dataset of ``n`` runs is generated in rounds. The first ``initial`` runs are the sampler's design
(``dataset.sampler``, e.g. uniform); the remaining ``n - initial`` are split evenly over ``rounds``. Before
each round a surrogate with member uncertainty (the ``ensemble`` plugin by default) is trained on every
successful row stored so far, scores ``candidates x m`` uniform candidate points by its members'
disagreement (the sum over features of the members' standard deviation over the feature's standard
deviation in the training rows), and the round simulates the ``m`` best candidates that lie at least
``min_gap`` apart in the unit cube (so a round does not pile onto one spot; if too few do, the best of
the rest fill the round).

Each round's points are written to ``_design.json`` in the store before they are simulated, so a killed
or time-limited generation resumes the same points (no refit). One process grows a design at a time
(``.design.lock``; a second one fails with one line). Raising ``n`` and ``rounds`` together adds
rounds to a finished design (the planned ones keep their points); other settings than the stored plan's
are refused. The settings and the plan file are :mod:`invphys.core.adaptive_plan`. Rows are stored as any generation's (a session per round in the metadata, with its
round number), so the store reads, verifies and joins like any other.

Why: on the orange peel's paper preset, two adaptive designs of 1,600 runs (800 uniform + 4 rounds of 200)
gave the shipped surrogate R^2 0.941-0.947 on 2,000 uniform test runs, against 0.925-0.938 for five uniform
designs of 1,600 runs (docs/results.md).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.adaptive_plan import (
    DESIGN_LOCK,
    PLAN_FILE,
    AdaptiveSettings,
    check_plan,
    disagreement,
    load_plan,
    pick_spread,
)
from invphys.core.atomic import write_json
from invphys.core.errors import InvphysError


def adaptive_settings(block: Any, n: int, planned_initial: int | None = None) -> AdaptiveSettings:
    """:meth:`AdaptiveSettings.of` for ``block``, an :class:`~invphys.core.spec.AdaptiveSection` or a mapping
    (validated here; bad input raises :class:`InvphysError`)."""
    from pydantic import ValidationError

    from invphys.core.spec import AdaptiveSection

    try:
        section = block if isinstance(block, AdaptiveSection) else AdaptiveSection.model_validate(block)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'block'}: {e['msg']}" for e in exc.errors())
        raise InvphysError(f"dataset.adaptive: {problems}") from None
    return AdaptiveSettings.of(section, n, planned_initial)


def uncertain_surrogate(settings: AdaptiveSettings, registry: Any) -> Any:
    """A fresh surrogate of ``settings.surrogate``; refused unless it reports member uncertainty."""
    from invphys.core.interfaces import Surrogate

    surrogate = registry.create("surrogate", dict(settings.surrogate))
    own = getattr(type(surrogate), "predict_with_uncertainty", None)
    if own is None or own is Surrogate.predict_with_uncertainty:  # the interface's default: a zero std
        raise InvphysError(f"dataset.adaptive needs a surrogate with member uncertainty (predict_with_uncertainty, "
                           f"e.g. 'ensemble'); {surrogate.name!r} has none")
    return surrogate


def propose_round(theta: np.ndarray, y: np.ndarray, m: int, settings: AdaptiveSettings, seed: int,
                  round_index: int, registry: Any) -> tuple[np.ndarray, dict[str, Any]]:
    """Train the surrogate on ``(theta, y)`` (unit-cube parameters, features) and return ``m`` new
    unit-cube points with a record of the fit and the scores."""
    surrogate = uncertain_surrogate(settings, registry)
    metrics = surrogate.fit(theta, y)
    rng = np.random.default_rng([seed, 104729, round_index])
    candidates = rng.random((settings.candidates * m, theta.shape[1]))
    _, std = surrogate.predict_with_uncertainty(candidates)
    score = disagreement(np.asarray(std, dtype=np.float64), y)
    chosen = pick_spread(candidates, score, m, settings.min_gap)
    record = {"round": round_index, "training_rows": len(theta),
              "surrogate_r2": _maybe_float(metrics.get("r2")) if isinstance(metrics, dict) else None,
              "candidates": len(candidates), "score_median_candidates": float(np.median(score)),
              "score_mean_chosen": float(score[chosen].mean())}
    return candidates[chosen], record


def _maybe_float(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) else None


def generate_adaptive(path: str | os.PathLike[str], *, n: int, sampler: str, seed: int, adaptive: Any,
                      limit_minutes: float | None, progress: bool, console: Any, registry: Any,
                      generate: Callable[..., Any], **common: Any) -> Any:
    """Generate the adaptive design of ``n`` runs into ``path`` (the arguments of
    :func:`~invphys.data.generate.generate_dataset`, which passes itself as ``generate``, the
    generation of one round's points); returns its :class:`GenerationSummary` summed over
    the initial design and the rounds, with ``design`` holding the rounds' records."""
    from invphys import registry as registry_module

    reg = registry or registry_module.default_registry()
    store_path = Path(path)
    stored = load_plan(store_path)
    settings = adaptive_settings(adaptive, n, None if stored is None else stored["key"].get("initial"))
    uncertain_surrogate(settings, reg)  # a bad surrogate block fails before anything is simulated
    plan_key = settings.key(n, sampler, seed)
    plan = check_plan(stored, store_path, plan_key)  # other settings than a stored plan's fail here too
    settings.round_sizes(n, [len(r["points"]) for r in plan["rounds"]])  # so does a bad extension
    with _design_lock(store_path):
        # under the lock, from the plan as it is now (another process may have planned a round meanwhile)
        plan = check_plan(load_plan(store_path), store_path, plan_key)
        sizes = settings.round_sizes(n, [len(r["points"]) for r in plan["rounds"]])
        return _grow(store_path, plan, plan_key, sizes, settings, n=n, sampler=sampler, seed=seed,
                     limit_minutes=limit_minutes, progress=progress, console=console, reg=reg, generate=generate,
                     **common)


@contextlib.contextmanager
def _design_lock(path: Path) -> Iterator[None]:
    """Hold ``path/.design.lock`` while a design grows: the store's own write lock is released between the
    rounds (while the surrogate trains), and two processes planning the same round would race on the plan."""
    from filelock import FileLock, Timeout

    if path.exists() and not path.is_dir():
        yield  # not a store: generation reports it
        return
    path.mkdir(parents=True, exist_ok=True)
    lock = FileLock(str(path / DESIGN_LOCK))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        raise InvphysError(f"another process is growing the adaptive design in {str(path)!r}; wait for it to "
                           "finish (or stop it: a later run resumes its rounds)") from None
    try:
        yield
    finally:
        lock.release()


def _grow(store_path: Path, plan: dict[str, Any], plan_key: dict[str, Any], sizes: list[int],
          settings: AdaptiveSettings, *, n: int, sampler: str, seed: int, limit_minutes: float | None,
          progress: bool, console: Any, reg: Any, generate: Callable[..., Any], **common: Any) -> Any:
    """The initial design, then each round (planned or planned now), under the design lock."""
    import time

    from invphys.core.dataset import DatasetStore, round_theta

    t0 = time.monotonic()

    def remaining() -> float | None:
        return None if limit_minutes is None else max(limit_minutes - (time.monotonic() - t0) / 60.0, 0.01)

    total = generate(store_path, n=settings.initial, sampler=sampler, seed=seed, limit_minutes=remaining(),
                     progress=progress, console=console, registry=reg, design={"adaptive": "initial"}, **common)
    total.requested = n
    total.design = {"adaptive": plan_key, "rounds": [r["record"] for r in plan["rounds"]]}
    offset = settings.initial
    if plan.pop("grown", False):
        write_json(store_path / PLAN_FILE, plan, indent=None)
    for k, m in enumerate(sizes):
        if total.stop_reason != "complete":
            break
        if k < len(plan["rounds"]):
            points = np.asarray(plan["rounds"][k]["points"], dtype=np.float64)
        else:
            data = DatasetStore(store_path).arrays(ok_only=True)
            if len(data.theta) < 2:
                raise InvphysError(f"dataset.adaptive: only {len(data.theta)} successful rows to train the "
                                   "surrogate on; the initial design failed")
            if progress:
                from rich.console import Console

                (console or Console(stderr=True)).print(
                    f"adaptive round {k + 1}/{settings.rounds}: training {settings.surrogate.get('type')!r} "
                    f"on {len(data.theta)} rows, choosing {m} points")
            points, record = propose_round(data.theta, data.y, m, settings, seed, k, reg)
            points = round_theta(points)
            plan["rounds"].append({"record": record, "points": points.tolist()})
            write_json(store_path / PLAN_FILE, plan, indent=None)
            total.design["rounds"].append(record)
        part = generate(store_path, n=m, sampler=sampler, seed=seed, points=points, index_offset=offset,
                        limit_minutes=remaining(), progress=progress, console=console, registry=reg,
                        design={"adaptive": "round", "round": k}, **common)
        offset += m
        _accumulate(total, part)
    total.wall_s = time.monotonic() - t0
    total.other_rows = max(total.total_rows - total.already_present - total.ran, 0)  # rows of no round
    if total.stop_reason == "complete" and not total.complete:
        total.stop_reason = "incomplete"
    return total


def _accumulate(total: Any, part: Any) -> None:
    total.already_present += part.already_present
    total.ran += part.ran
    total.ok += part.ok
    total.failed += part.failed
    total.stop_reason = part.stop_reason
    total.total_rows, total.total_ok, total.total_failed = part.total_rows, part.total_ok, part.total_failed
    total.devices = sorted(set(total.devices) | set(part.devices))
    total.backends = sorted(set(total.backends) | set(part.backends))
