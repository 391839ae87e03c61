"""Adaptive against uniform designs of 1,600 and 2,000 paper-preset runs: table and figure (issue 11).

    .venv/bin/python results/orange_peel_paper_surrogate/v030/design/make_report.py

Inputs (all CPU runs of the shipped ensemble and the paper MLP; commands inside each JSON):

* ``uniform_vs_adaptive.json`` (``uniform_vs_adaptive.py``): disjoint uniform designs of 1,600 (five) and 2,000
  (four) runs and the two adaptive designs at 1,600 and 2,000 runs, each scored on all 2,000 uniform runs of
  ``datasets/orange_peel_paper``;
* ``benchmarks/results/simulator_surrogate_paper_v030_adaptive[_seed3]_{split0,split1,split2,all}.json``
  (``bench_simulator_surrogate.py --train-store``, made when the stores held 1,600 rows: ``--train-first 1600``
  re-makes them): the adaptive stores' first 1,600 rows on the three held-out splits of 400 and on all 2,000
  rows, with the adaptive design's learning curve (rounds) on split 0;
* ``benchmarks/results/simulator_surrogate_paper_v030_adaptive[_seed3]2000_{split0,split1,split2,all}.json``: the
  same for all 2,000 rows of each adaptive store (``_all``: learning curve 250 - 2,000 on all 2,000 test rows);
* ``bar_check_10k.json`` (``bar_check_10k.py``): the 2,000-run adaptive designs on all 10,000 uniform runs;
* ``benchmarks/results/simulator_surrogate_paper_v030_seed1first2000_all.json``: a uniform 2,000-run design (the
  seed-1 store's first 2,000 rows) with its learning curve on the same 2,000 test rows;
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
ADAPTIVE = {"1,600 adaptive (seed 2)": "simulator_surrogate_paper_v030_adaptive",
            "1,600 adaptive (seed 3)": "simulator_surrogate_paper_v030_adaptive_seed3",
            "2,000 adaptive (seed 2)": "simulator_surrogate_paper_v030_adaptive2000",
            "2,000 adaptive (seed 3)": "simulator_surrogate_paper_v030_adaptive_seed32000"}
CURVES = {"uniform (seed-1 store)": ("simulator_surrogate_paper_v030_seed1first2000_all.json", "tab:gray"),
          "adaptive, seed 2": ("simulator_surrogate_paper_v030_adaptive2000_all.json", "tab:blue"),
          "adaptive, seed 3": ("simulator_surrogate_paper_v030_adaptive_seed32000_all.json", "tab:orange")}


def load(name: str) -> dict | None:
    path = BENCH / name
    return json.loads(path.read_text()) if path.exists() else None


def main() -> dict:
    uva = json.loads((HERE / "uniform_vs_adaptive.json").read_text())
    names = uva["feature_names"]
    rows: dict[str, dict] = {}
    uni = {s: load(f) for s, f in UNIFORM_SPLITS.items()}
    rows["1,600 uniform (main store's training rows)"] = {
        model: {f"split{s}": [r["models"][model]["r2"], r["models"][model]["r2_min_feature"]] for s, r in uni.items()}
        for model in ("ensemble", "mlp_paper")}
    for label, stem in ADAPTIVE.items():
        runs = {part: load(f"{stem}_{part}.json") for part in ("split0", "split1", "split2", "all")}
        rows[label] = {model: {part: [r["models"][model]["r2"], r["models"][model]["r2_min_feature"]]
                               for part, r in runs.items() if r is not None}
                       for model in ("ensemble", "mlp_paper")}
    for n in (1600, 2000):
        base_all = load(f"simulator_surrogate_paper_v030_seed1first{n}_all.json")
        if base_all is not None:
            rows[f"{n:,} uniform (seed-1 store's first {n:,} rows)"] = {
                model: {"all": [base_all["models"][model]["r2"], base_all["models"][model]["r2_min_feature"]]}
                for model in ("ensemble", "mlp_paper")}
    per_feature = {label: r["r2_per_feature"] for label, r in uva["runs"].items()
                   if label in ("uniform2000_block_0", "adaptive2000_seed_0", "adaptive3_2000_seed_0",
                                "adaptive2000_mlp_paper", "adaptive3_2000_mlp_paper")}
    all_rows = {k: [v["r2"], v["worst"], v.get("r2_ci95")] for k, v in uva["runs"].items()}
    report = {"bar": [BAR_MEAN, BAR_MIN], "by_design": rows, "all_rows_runs": all_rows,
              "all_rows_summary": summarise(uva["runs"]), "per_feature_all_rows": per_feature,
              "feature_names": names}
    fmt = lambda v: f"{v[0]:.3f} ({v[1]:.3f})" if v else "-"  # noqa: E731
    md = ["| training runs | model | split 0 | split 1 | split 2 | all 2,000 |", "|---|---|---|---|---|---|"]
    for label, models in rows.items():
        for model, parts in models.items():
            md.append(f"| {label} | {model} | " + " | ".join(fmt(parts.get(p)) for p in ("split0", "split1", "split2", "all"))
                      + " |")
    ci = lambda v: f"[{v[0]:.4f}, {v[1]:.4f}]" if v else "-"  # noqa: E731
    md += ["", "| all 2,000 uniform rows (ensemble unless `mlp_paper`) | mean R^2 (worst feature) | 95 % interval (test rows) |",
           "|---|---|---|"]
    md += [f"| {k} | {v[0]:.4f} ({v[1]:.3f}) | {ci(v[2])} |" for k, v in all_rows.items()]
    md += ["", "| feature (all 2,000 test rows) | " + " | ".join(per_feature) + " |", "|---" * (len(per_feature) + 1) + "|"]
    md += [f"| {f} | " + " | ".join(f"{per_feature[k][f]:.3f}" for k in per_feature) + " |" for f in names]
    md += ["| **mean** | " + " | ".join(f"**{np.mean(list(per_feature[k].values())):.4f}**" for k in per_feature) + " |"]
    bar10k_path = HERE / "bar_check_10k.json"
    if bar10k_path.exists():
        bar10k = json.loads(bar10k_path.read_text())
        report["bar_check_10k"] = {k: [v["r2"], v["worst"], v["r2_ci95"]] for k, v in bar10k["runs"].items()}
        md += ["", f"| all {bar10k['n_test']:,} uniform runs (`bar_check_10k.py`), ensemble | mean R^2 (worst feature) | "
               "95 % interval (test rows) |", "|---|---|---|"]
        md += [f"| {k} | {v['r2']:.4f} ({v['worst']:.3f}) | {ci(v['r2_ci95'])} |" for k, v in bar10k["runs"].items()]
    (HERE / "design_report.json").write_text(json.dumps(report, indent=1) + "\n")
    (HERE / "design_report.md").write_text("\n".join(md) + "\n")
    plot(uva, {label: (load(f), colour) for label, (f, colour) in CURVES.items()})
    print("\n".join(md))
    return report


def summarise(runs: dict) -> dict:
    out = {}
    for prefix in ("uniform_block", "adaptive_seed", "adaptive3_seed", "uniform2000_block", "adaptive2000_seed",
                   "adaptive3_2000_seed"):
        v = [r["r2"] for k, r in runs.items() if k.startswith(prefix) and not k.endswith("mlp_paper")]
        w = [r["worst"] for k, r in runs.items() if k.startswith(prefix) and not k.endswith("mlp_paper")]
        if v:
            out[prefix] = {"n": len(v), "mean": float(np.mean(v)), "min": float(min(v)), "max": float(max(v)),
                           "worst_feature_min": float(min(w))}
    return out


def plot(uva: dict, curves: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    groups = [("uniform_block", "uniform", "tab:gray", 1600), ("adaptive_seed", "adaptive, seed 2", "tab:blue", 1600),
              ("adaptive3_seed", "adaptive, seed 3", "tab:orange", 1600),
              ("uniform2000_block", "uniform", "tab:gray", 2000), ("adaptive2000_seed", "adaptive, seed 2", "tab:blue", 2000),
              ("adaptive3_2000_seed", "adaptive, seed 3", "tab:orange", 2000)]
    for i, (prefix, label, colour, n) in enumerate(groups):
        v = [r["r2"] for k, r in uva["runs"].items() if k.startswith(prefix) and not k.endswith("mlp_paper")]
        x = i + (i >= 3) * 0.6
        a.scatter(np.full(len(v), x) + np.linspace(-0.1, 0.1, len(v)), v, color=colour,
                  label=label if n == 1600 else None)
    a.axhline(BAR_MEAN, color="k", ls="--", lw=0.8, label="issue 11 bar (0.95)")
    a.set_xticks([1, 4.6], ["1,600 training runs", "2,000 training runs"])
    a.set_ylabel("mean R^2 on all 2,000 uniform test runs")
    a.set_title("designs of the same size, shipped ensemble")
    a.legend(fontsize=8, loc="lower right")
    for label, (run, colour) in curves.items():
        if run is None or "ensemble" not in run.get("learning_curves", {}):
            continue
        c = run["learning_curves"]["ensemble"] + [{"n_train": run["n_train"], "r2": run["models"]["ensemble"]["r2"]}]
        b.plot([x["n_train"] for x in c], [x["r2"] for x in c], "o-", color=colour, label=label)
    b.axhline(BAR_MEAN, color="k", ls="--", lw=0.8)
    b.set_xlabel("training runs (adaptive: 800 uniform, then rounds of 200)")
    b.set_ylabel("mean R^2, all 2,000 uniform test runs")
    b.set_title("learning curves, shipped ensemble")
    b.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(HERE / "adaptive_design.png", dpi=110)
    shutil.copy(HERE / "adaptive_design.png", ROOT / "docs" / "orange-peel" / "adaptive_design.png")


if __name__ == "__main__":
    main()
