"""Adaptive against uniform designs of 1,600 paper-preset runs: table and figure (issue 11).

    .venv/bin/python results/orange_peel_paper_surrogate/v030/design/make_report.py

Inputs (all CPU runs of the shipped ensemble and the paper MLP; commands inside each JSON):

* ``uniform_vs_adaptive.json`` (``uniform_vs_adaptive.py``): five disjoint uniform 1,600-run designs and the two
  adaptive designs, each scored on all 2,000 uniform runs of ``datasets/orange_peel_paper``;
* ``benchmarks/results/simulator_surrogate_paper_v030_adaptive[_seed3]_{split0,split1,split2,all}.json``
  (``bench_simulator_surrogate.py --train-store``): the adaptive stores on the three held-out splits of 400 and
  on all 2,000 rows, with the adaptive design's learning curve (rounds) on split 0;
* ``benchmarks/results/simulator_surrogate_paper_v030[_seed1,_seed2].json``: the main store's own 1,600 uniform
  training rows on the same splits, and its learning curve.

Writes ``design_report.json`` and ``design_report.md`` here and ``adaptive_design.png`` here and in
``docs/orange-peel/``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[3]
BENCH = ROOT / "benchmarks" / "results"
BAR_MEAN, BAR_MIN = 0.95, 0.85
UNIFORM_SPLITS = {0: "simulator_surrogate_paper_v030.json", 1: "simulator_surrogate_paper_v030_seed1.json",
                  2: "simulator_surrogate_paper_v030_seed2.json"}
ADAPTIVE = {"adaptive (seed 2)": "simulator_surrogate_paper_v030_adaptive",
            "adaptive (seed 3)": "simulator_surrogate_paper_v030_adaptive_seed3"}


def load(name: str) -> dict | None:
    path = BENCH / name
    return json.loads(path.read_text()) if path.exists() else None


def main() -> dict:
    uva = json.loads((HERE / "uniform_vs_adaptive.json").read_text())
    names = uva["feature_names"]
    rows: dict[str, dict] = {}
    uni = {s: load(f) for s, f in UNIFORM_SPLITS.items()}
    rows["uniform (main store's 1,600 training rows)"] = {
        model: {f"split{s}": [r["models"][model]["r2"], r["models"][model]["r2_min_feature"]] for s, r in uni.items()}
        for model in ("ensemble", "mlp_paper")}
    for label, stem in ADAPTIVE.items():
        runs = {part: load(f"{stem}_{part}.json") for part in ("split0", "split1", "split2", "all")}
        rows[label] = {model: {part: [r["models"][model]["r2"], r["models"][model]["r2_min_feature"]]
                               for part, r in runs.items() if r is not None}
                       for model in ("ensemble", "mlp_paper")}
    base_all = load("simulator_surrogate_paper_v030_seed1first1600_all.json")
    rows["uniform (seed-1 store's first 1,600 rows)"] = {
        model: {"all": [base_all["models"][model]["r2"], base_all["models"][model]["r2_min_feature"]]}
        for model in ("ensemble", "mlp_paper")}
    all_rows = {k: [v["r2"], v["worst"]] for k, v in uva["runs"].items()}
    report = {"bar": [BAR_MEAN, BAR_MIN], "by_design": rows, "all_rows_runs": all_rows,
              "all_rows_summary": summarise(uva["runs"]), "feature_names": names}
    (HERE / "design_report.json").write_text(json.dumps(report, indent=1) + "\n")

    fmt = lambda v: f"{v[0]:.3f} ({v[1]:.3f})" if v else "-"  # noqa: E731
    md = ["| training rows (1,600 runs) | model | split 0 | split 1 | split 2 | all 2,000 |", "|---|---|---|---|---|---|"]
    for label, models in rows.items():
        for model, parts in models.items():
            md.append(f"| {label} | {model} | " + " | ".join(fmt(parts.get(p)) for p in ("split0", "split1", "split2", "all"))
                      + " |")
    md += ["", "| all 2,000 uniform rows, shipped ensemble | mean R^2 (worst feature) |", "|---|---|"]
    md += [f"| {k} | {v[0]:.4f} ({v[1]:.3f}) |" for k, v in all_rows.items()]
    (HERE / "design_report.md").write_text("\n".join(md) + "\n")
    plot(uva, uni[0], [load(f"{stem}_split0.json") for stem in ADAPTIVE.values()])
    print("\n".join(md))
    return report


def summarise(runs: dict) -> dict:
    out = {}
    for prefix in ("uniform_block", "adaptive_seed", "adaptive3_seed"):
        v = [r["r2"] for k, r in runs.items() if k.startswith(prefix)]
        w = [r["worst"] for k, r in runs.items() if k.startswith(prefix)]
        if v:
            out[prefix] = {"n": len(v), "mean": float(np.mean(v)), "min": float(min(v)), "max": float(max(v)),
                           "worst_feature_min": float(min(w))}
    return out


def plot(uva: dict, uniform0: dict, adaptive0: list[dict | None]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    groups = [("uniform_block", "5 uniform designs", "tab:gray"), ("adaptive_seed", "adaptive, seed 2", "tab:blue"),
              ("adaptive3_seed", "adaptive, seed 3", "tab:orange")]
    for i, (prefix, label, colour) in enumerate(groups):
        v = [r["r2"] for k, r in uva["runs"].items() if k.startswith(prefix)]
        a.scatter(np.full(len(v), i) + np.linspace(-0.1, 0.1, len(v)), v, color=colour, label=label)
    a.axhline(BAR_MEAN, color="k", ls="--", lw=0.8, label="issue 11 bar (0.95)")
    a.set_xticks(range(len(groups)), [g[1] for g in groups])
    a.set_ylabel("mean R^2 on all 2,000 uniform runs")
    a.set_title("1,600 training runs, shipped ensemble")
    a.legend(fontsize=8, loc="lower right")
    curve = uniform0["learning_curves"]["ensemble"]
    b.plot([c["n_train"] for c in curve], [c["r2"] for c in curve], "o-", color="tab:gray", label="uniform (main store)")
    for run, (_, label, colour) in zip(adaptive0, groups[1:], strict=True):
        if run is None or "ensemble" not in run.get("learning_curves", {}):
            continue
        c = run["learning_curves"]["ensemble"]
        b.plot([x["n_train"] for x in c], [x["r2"] for x in c], "o-", color=colour, label=label + " (rounds)")
    b.axhline(BAR_MEAN, color="k", ls="--", lw=0.8)
    b.set_xlabel("training runs")
    b.set_ylabel("mean R^2, split 0's 400 held-out runs")
    b.set_title("learning curve: 800 uniform, then 4 rounds")
    b.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(HERE / "adaptive_design.png", dpi=110)
    shutil.copy(HERE / "adaptive_design.png", ROOT / "docs" / "orange-peel" / "adaptive_design.png")


if __name__ == "__main__":
    main()
