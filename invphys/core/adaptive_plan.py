"""Adaptive design's settings and stored plan (``dataset.adaptive``), below the registry.

The store (:meth:`~invphys.core.dataset.DatasetStore.manifest`) describes a stored plan and the spec checks a
block's settings through this module; growing a design (training a surrogate, simulating its rounds) is
:mod:`invphys.data.adaptive`, which tells how a design is chosen and resumed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError

PLAN_FILE = "_design.json"
#: held by the one process growing a store's design (the store's ``.lock`` is released between rounds)
DESIGN_LOCK = ".design.lock"
PLAN_FORMAT = 1
#: settings that fix the points already planned; ``n`` and ``rounds`` may grow to add rounds
FIXED: tuple[str, ...] = ("sampler", "seed", "initial", "surrogate", "candidates", "min_gap")


@dataclass(frozen=True)
class AdaptiveSettings:
    """A ``dataset.adaptive`` block (:class:`~invphys.core.spec.AdaptiveSection`, which holds the defaults)
    with ``initial`` resolved for ``n`` runs."""

    initial: int
    rounds: int
    surrogate: dict[str, Any]
    candidates: int
    min_gap: float

    @classmethod
    def of(cls, section: Any, n: int, planned_initial: int | None = None) -> AdaptiveSettings:
        """Check a validated ``dataset.adaptive`` block (an :class:`~invphys.core.spec.AdaptiveSection`; a
        mapping is validated by :func:`invphys.data.adaptive.adaptive_settings`) for ``n`` runs; bad input
        raises :class:`InvphysError`. An unset ``initial`` is ``planned_initial`` (a stored plan's, so a design
        grows without restating it), else ``n // 2``."""
        initial = section.initial if section.initial is not None else planned_initial
        out = cls(initial=initial if initial is not None else n // 2, rounds=section.rounds,
                  surrogate=dict(section.surrogate), candidates=section.candidates, min_gap=section.min_gap)
        if not 0 < out.initial < n:
            raise InvphysError(f"dataset.adaptive.initial must be in [1, n - 1] = [1, {n - 1}], got {out.initial}")
        if n - out.initial < out.rounds:
            raise InvphysError(f"dataset.adaptive: {n - out.initial} adaptive rows cannot fill {out.rounds} rounds")
        return out

    def round_sizes(self, n: int, planned: list[int] | None = None) -> list[int]:
        """Runs per round: the ``planned`` rounds keep their sizes, the others share the rest evenly."""
        planned = list(planned or [])
        left, rounds_left = n - self.initial - sum(planned), self.rounds - len(planned)
        if rounds_left < 0 or left < rounds_left or (rounds_left == 0 and left > 0):
            raise InvphysError(
                f"dataset.adaptive: {len(planned)} rounds of {sum(planned)} runs are already planned after the "
                f"{self.initial} initial ones; n = {n} and rounds = {self.rounds} cannot extend them (raise "
                "`rounds` with `n` to add rounds)")
        base, extra = divmod(left, rounds_left) if rounds_left else (0, 0)
        return planned + [base + (k < extra) for k in range(rounds_left)]

    def key(self, n: int, sampler: str, seed: int) -> dict[str, Any]:
        """The design's settings; all but ``n`` and ``rounds`` (:data:`FIXED`) must match a stored plan's."""
        return {"n": n, "sampler": sampler, "seed": seed, "initial": self.initial, "rounds": self.rounds,
                "surrogate": self.surrogate, "candidates": self.candidates, "min_gap": self.min_gap}


def disagreement(std: np.ndarray, y_train: np.ndarray) -> np.ndarray:
    """Per candidate: the sum over features of the members' std over the feature's training std."""
    scale = y_train.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    return (std / scale).sum(axis=1)


def pick_spread(points: np.ndarray, score: np.ndarray, m: int, min_gap: float) -> np.ndarray:
    """Indices of the ``m`` highest-scoring points, greedily, each >= ``min_gap`` from those picked
    before it; if fewer qualify, the best of the others fill up to ``m``."""
    order = np.argsort(-score, kind="stable")
    picked: list[int] = []
    for i in order:
        if len(picked) == m:
            break
        if picked and np.sqrt(((points[picked] - points[i]) ** 2).sum(axis=1)).min() < min_gap:
            continue
        picked.append(int(i))
    if len(picked) < m:
        chosen = set(picked)
        picked += [int(i) for i in order if int(i) not in chosen][: m - len(picked)]
    return np.asarray(picked, dtype=np.int64)


def load_plan(path: Path) -> dict[str, Any] | None:
    """The parsed ``_design.json`` of the store at ``path`` (None when absent); unreadable raises."""
    import json

    plan_path = path / PLAN_FILE
    if not plan_path.exists():
        return None
    try:
        plan = json.loads(plan_path.read_text())
        if not (isinstance(plan.get("key"), dict) and isinstance(plan["rounds"], list)
                and all("points" in r and "record" in r for r in plan["rounds"])):
            raise ValueError
    except Exception:
        raise InvphysError(f"{plan_path} is unreadable; move it away to plan the adaptive rounds afresh "
                           "(rows already stored are kept)") from None
    return plan


def check_plan(plan: dict[str, Any] | None, path: Path, key: dict[str, Any]) -> dict[str, Any]:
    """The stored ``plan`` (or a new one) for a design with settings ``key``; other fixed settings raise."""
    import json

    if plan is None:
        return {"format": PLAN_FORMAT, "key": key, "rounds": []}
    have, want = plan.get("key") or {}, json.loads(json.dumps(key))
    if any(have.get(k) != want[k] for k in FIXED):
        raise InvphysError(f"the dataset at {str(path)!r} was grown with other adaptive settings "
                           f"({ {k: have.get(k) for k in FIXED} }); generate into a new directory or use the same "
                           "settings (only n and rounds may grow)")
    plan["grown"] = have != want  # n or rounds raised: the plan's record of them is rewritten
    plan["key"] = want
    return plan


def describe_design(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The adaptive plan stored in a dataset (its settings and each planned round's record), or None."""
    try:
        plan = load_plan(Path(path))
    except InvphysError:
        return {"adaptive": None, "problem": f"{PLAN_FILE} is unreadable"}
    return None if plan is None else {"adaptive": plan["key"], "rounds": [r["record"] for r in plan["rounds"]]}


