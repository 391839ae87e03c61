"""Summary and figure of the refined chain: active learning -> polish pass 1 -> pass 2 -> re-selection.

Reads the committed results only (no simulation): the active + polish report, the second polish's
benchmark JSON (with its ``--recheck 2`` re-simulations) and the robust re-selection's JSON and answers.
Writes ``summary.json`` (per stage: mean R_actual with its 95 % bootstrap interval over the 100 targets,
the paired difference against the nearest-neighbour lookup, and the cumulative simulator runs and GPU
seconds per target) and ``protocol.png`` (the protocol's plot) next to this file.

    python results/orange_peel_paper_active_polish2/make_summary.py
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from invphys.evaluation.plots import plot_protocol
from invphys.evaluation.protocol import actual_score
from invphys.evaluation.stats import bootstrap_mean_ci, paired_difference

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]


def main() -> None:
    report = json.loads((ROOT / "results/orange_peel_paper_active_polish/report.json").read_text())
    pol = json.loads((HERE / "polish_active_again_paper_h100.json").read_text())
    rr = json.loads((HERE / "robust_reselect_h100.json").read_text())
    fresh = np.load(HERE / "robust_reselect_h100.answers.npz")["r_fresh"]
    n = pol["targets"]

    def label(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows = sorted((r for r in report["rows"] if r["optimizer"] == name), key=lambda r: r["target_index"])[:n]
        return (np.array([actual_score(r) for r in rows]), np.array([r.get("simulator_runs") or 0 for r in rows], float),
                np.array([r.get("wall_time_s") or 0.0 for r in rows], float))

    per = pol["per_target"]
    lookup = np.array([p["lookup"] for p in per])
    r_active, runs_active, secs_active = label("active_learning")
    r_pass1, runs_pass1, secs_pass1 = label("active_polished")
    assert np.allclose(r_pass1, [p["start"] for p in per], atol=1e-3), "pass 2 did not start at pass 1's answers"
    floor, _, _ = label("noise_floor")
    runs_pass2 = np.array([p["runs"] for p in per], float)
    recheck = np.nanmean(np.asarray(pol["recheck"]["per_target"], float), axis=1)
    # GPU seconds per target: the report's per-target cost for the first two stages (retraining included),
    # then each later step's simulator seconds spread over the 100 targets
    active_s = secs_pass1.mean()
    pass2_s, recheck_s, reselect_s = (pol["simulator_seconds"] / n, pol["recheck"]["seconds"] / n,
                                      rr["simulator_seconds"] / n)
    stages = [
        ("nearest_neighbour", "reference", lookup, 0.0, 0.0),
        ("active_learning (6 rounds)", "method", r_active, runs_active.mean(), secs_active.mean()),
        ("+ polish pass 1 (below 0.9)", "method", r_pass1, runs_pass1.mean(), active_s),
        ("+ polish pass 2 (below 0.95), best of N", "method", np.array([p["final"] for p in per]),
         runs_pass1.mean() + runs_pass2.mean(), active_s + pass2_s),
        ("  the same answers re-simulated x2", "method", recheck,
         runs_pass1.mean() + runs_pass2.mean() + pol["recheck"]["runs"] / n, active_s + pass2_s + recheck_s),
        ("+ robust re-selection, fresh runs x2", "method", fresh.mean(axis=1),
         runs_pass1.mean() + runs_pass2.mean() + (pol["recheck"]["runs"] + rr["runs"]) / n,
         active_s + pass2_s + recheck_s + reselect_s),
        ("noise floor (true parameters)", "baseline", floor, 1.0, np.nan),
    ]
    summary: dict[str, dict] = {}
    for name, role, r, runs, secs in stages:
        m, lo, hi = bootstrap_mean_ci(r)
        summary[name] = {"role": role, "n_validated": int(np.isfinite(r).sum()), "r_actual_mean": m,
                         "r_actual_ci95": [lo, hi], "simulator_runs_per_target": runs,
                         "gpu_seconds_per_target": None if np.isnan(secs) else secs,
                         "vs_nearest_neighbour": None if role == "reference" else paired_difference(r, lookup)}
    out = {"targets": n, "selection": pol["selection"], "device": rr["device"],
           "simulator_version": rr["simulator_version"], "config_hash": rr["config_hash"],
           "refined_bar": 0.92, "stages": summary}
    (HERE / "summary.json").write_text(json.dumps(out, indent=1) + "\n")
    plot_protocol(summary, HERE / "protocol.png", reference="nearest_neighbour",
                  title="Orange peel, paper preset, 100 held-out targets: the refined chain, stage by stage (one H100)")
    for name, s in summary.items():
        d = s["vs_nearest_neighbour"]
        print(f"{name:45s} {s['r_actual_mean']:.4f} [{s['r_actual_ci95'][0]:.4f}, {s['r_actual_ci95'][1]:.4f}]"
              + (f"  vs lookup {d['mean_diff']:+.4f} [{d['ci95'][0]:+.4f}, {d['ci95'][1]:+.4f}]" if d else "")
              + f"  runs/target {s['simulator_runs_per_target']:.1f}")


if __name__ == "__main__":
    main()
