"""Surrogate quality on the simulator 0.3.0 paper data: per-feature table over three splits, learning curve.

    .venv/bin/python results/orange_peel_paper_surrogate/v030/make_report.py

Inputs (CPU, the real plugins, `benchmarks/bench_simulator_surrogate.py`; commands inside each JSON):
``benchmarks/results/simulator_surrogate_paper_v030.json`` (split seed 0: ensemble, paper MLP, one network
with the ensemble's settings, learning curves of all three) and ``..._v030_seed{1,2}.json`` (ensemble and
paper MLP on split seeds 1 and 2). Writes ``surrogate_quality_v030.{json,md}`` here and
``learning_curve_v030.png`` here and in docs/orange-peel/.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent.parent
BENCH = ROOT / "benchmarks" / "results"
BAR_MEAN, BAR_MIN = 0.95, 0.85
RUNS = {0: "simulator_surrogate_paper_v030.json", 1: "simulator_surrogate_paper_v030_seed1.json",
        2: "simulator_surrogate_paper_v030_seed2.json"}


def main() -> dict:
    runs = {s: json.loads((BENCH / f).read_text()) for s, f in RUNS.items()}
    names = runs[0]["feature_names"]
    table: dict = {}
    for model in ("ensemble", "mlp_paper"):
        per_seed = {s: r["models"][model] for s, r in runs.items() if model in r["models"]}
        table[model] = {
            "mean_r2_by_split": {s: m["r2"] for s, m in per_seed.items()},
            "worst_by_split": {s: [min(m["r2_per_feature"], key=m["r2_per_feature"].get),
                                   m["r2_min_feature"]] for s, m in per_seed.items()},
            "per_feature_by_split": {n: [per_seed[s]["r2_per_feature"][n] for s in sorted(per_seed)] for n in names},
            "bar_met_by_split": {s: bool(m["r2"] >= BAR_MEAN and m["r2_min_feature"] >= BAR_MIN)
                                 for s, m in per_seed.items()},
        }
    curves = {label: [(c["n_train"], c["r2"], c["r2_min_feature"]) for c in curve]
              for label, curve in runs[0]["learning_curves"].items()}
    report = {"dataset": runs[0]["dataset"], "identity": runs[0]["identity"], "fingerprint": runs[0]["fingerprint"],
              "sources": [f"benchmarks/results/{f}" for f in RUNS.values()], "bar": [BAR_MEAN, BAR_MIN],
              "models": table, "curves_split0": curves}
    (HERE / "surrogate_quality_v030.json").write_text(json.dumps(report, indent=1))
    md = ["| feature | ensemble, splits 0 / 1 / 2 | paper MLP, splits 0 / 1 / 2 |", "|---|---|---|"]
    for n in names:
        cells = [" / ".join(f"{v:.3f}" for v in table[m]["per_feature_by_split"][n]) for m in ("ensemble", "mlp_paper")]
        md.append(f"| {n} | {cells[0]} | {cells[1]} |")
    for key, label in (("mean_r2_by_split", "**mean**"),):
        cells = [" / ".join(f"{v:.3f}" for v in table[m][key].values()) for m in ("ensemble", "mlp_paper")]
        md.append(f"| {label} | {cells[0]} | {cells[1]} |")
    cells = [" / ".join(f"{w[1]:.3f}" for w in table[m]["worst_by_split"].values()) for m in ("ensemble", "mlp_paper")]
    md.append(f"| worst | {cells[0]} | {cells[1]} |")
    md += ["", "| curve, split 0 (mean / worst) | " + " | ".join(f"{n:,}" for n, _, _ in curves["ensemble"]) + " |",
           "|---|" + "---:|" * len(curves["ensemble"])]
    for label, pts in curves.items():
        md.append(f"| {label} | " + " | ".join(f"{r:.3f} / {w:.3f}" for _, r, w in pts) + " |")
    (HERE / "surrogate_quality_v030.md").write_text("\n".join(md) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for label, pts in curves.items():
        n, r2, worst = (np.array(v) for v in zip(*pts, strict=True))
        line, = ax.plot(n, r2, "o-", label=f"{label} (mean)")
        ax.plot(n, worst, "s--", color=line.get_color(), alpha=0.6, label=f"{label} (worst feature)")
    ax.axhline(BAR_MEAN, color="k", lw=0.8, ls=":")
    ax.axhline(BAR_MIN, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("training rows (simulator 0.3.0, paper preset)")
    ax.set_ylabel("held-out R^2 (400 rows, split 0)")
    ax.set_ylim(0.4, 1.0)
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    fig.savefig(HERE / "learning_curve_v030.png", dpi=110)
    fig.savefig(ROOT / "docs" / "orange-peel" / "surrogate_learning_curve_v030.png", dpi=110)
    return report


if __name__ == "__main__":
    r = main()
    print(json.dumps({m: {"mean": v["mean_r2_by_split"], "worst": v["worst_by_split"]} for m, v in r["models"].items()},
                     indent=1))
