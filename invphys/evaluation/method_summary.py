"""The protocol's per-method summary: the machine-readable part of ``report.json``.

Input rows are the report's merged rows (one per method and problem) with at least ``optimizer``,
``problem``, ``target_index``, ``validated``, ``r_actual``, ``r_surrogate``, ``gap``, ``failure``,
``evaluations``, ``wall_time_s`` and optionally ``simulator_runs``, ``simulator_time_s``, ``device`` and ``role``.
A validation run that failed scores R_actual = 0 (the method's answer broke the simulator).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from invphys.evaluation.stats import bootstrap_mean_ci, paired_difference


def actual_score(row: dict[str, Any]) -> float:
    """R_actual of a row for the statistics: its value, 0 for a failed run, NaN when not validated."""
    if not row.get("validated"):
        return float("nan")
    v = row.get("r_actual")
    if v is not None and np.isfinite(v):
        return float(v)
    return 0.0 if row.get("failure") else float("nan")


def _num(rows: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in rows], dtype=np.float64)


def _mean(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else None


def _by_target(rows: list[dict[str, Any]], label: str) -> dict[int, dict[str, Any]]:
    return {int(r["target_index"]): r for r in rows
            if r["optimizer"] == label and r["problem"] == "target" and r.get("target_index") is not None}


def method_summary(rows: list[dict[str, Any]], label: str, reference: dict[int, dict[str, Any]] | None,
                   reference_label: str, ks: list[int] | None = None, n_boot: int = 2000,
                   confidence: float = 0.95, seed: int = 0) -> dict[str, Any]:
    """Statistics of one method over target indices ``ks`` (default all its targets)."""
    mine = _by_target(rows, label)
    ks = sorted(mine) if ks is None else [k for k in ks if k in mine]
    sel = [mine[k] for k in ks]
    val = [r for r in sel if r.get("validated")]
    act = np.array([actual_score(r) for r in val], dtype=np.float64)
    mean, lo, hi = bootstrap_mean_ci(act, n_boot, confidence, seed)
    out: dict[str, Any] = {
        "n_targets": len(sel), "n_validated": len(val), "failed": sum(1 for r in val if r.get("failure")),
        "r_actual_mean": mean if np.isfinite(mean) else None,
        "r_actual_ci95": [lo, hi] if np.isfinite(mean) else None,
        "r_surrogate_mean": _mean(_num(val, "r_surrogate")) if val else _mean(_num(sel, "r_surrogate")),
        "gap_mean": _mean(_num(val, "gap")),
        "evaluations": _mean(_num(sel, "evaluations")),
        "simulator_runs": _mean(_num(sel, "simulator_runs")) or 0.0,
        "wall_time_s": _mean(_num(sel, "wall_time_s")),
        "simulator_time_s": _mean(_num(sel, "simulator_time_s")),  # from the runs' own stats (replays too)
    }
    key = f"vs_{reference_label}"
    if reference is not None and label != reference_label:
        both = [k for k in ks if k in reference and mine[k].get("validated") and reference[k].get("validated")]
        diff = paired_difference([actual_score(mine[k]) for k in both],
                                 [actual_score(reference[k]) for k in both], n_boot, confidence, seed)
        out[key] = {**diff, "mean_diff": diff["mean_diff"] if diff["n"] else None,
                    "ci95": diff["ci95"] if diff["n"] else None}
    else:
        out[key] = None
    return out


def protocol_summary(rows: list[dict[str, Any]], set_labels: list[str] | None = None,
                     reference_label: str = "nearest_neighbour", n_boot: int = 2000,
                     confidence: float = 0.95, seed: int = 0) -> dict[str, dict[str, Any]]:
    """``{label: summary}`` for every method with target rows, baselines included.

    ``set_labels[k]`` names target k's set (``farthest_point``/``random``); with more than one set,
    each summary gets ``by_set`` with the same statistics per set.
    """
    targets = [r for r in rows if r["problem"] == "target"]
    reference = _by_target(rows, reference_label) or None
    out: dict[str, dict[str, Any]] = {}
    sets = sorted(set(set_labels)) if set_labels else []
    for label in dict.fromkeys(r["optimizer"] for r in targets):
        first = next(r for r in targets if r["optimizer"] == label)
        s = {"type": first.get("type"), "role": first.get("role", "optimizer"), "space": first.get("space"),
             "evaluator": first.get("evaluator"), "device": first.get("device"),
             **method_summary(rows, label, reference, reference_label, None, n_boot, confidence, seed)}
        if len(sets) > 1 and set_labels:
            s["by_set"] = {name: method_summary(rows, label, reference, reference_label,
                                                [k for k, lab in enumerate(set_labels) if lab == name],
                                                n_boot, confidence, seed) for name in sets}
        out[label] = s
    return out
