"""Build surrogate_quality.{json,md} and learning_curve.png (also docs/orange-peel/) from the committed benchmark JSONs.

    .venv/bin/python results/orange_peel_paper_surrogate/make_report.py

Inputs: ``benchmarks/results/simulator_surrogate_paper_{mlp,ensemble}.json`` (CPU, the real plugins),
``benchmarks/results/simulator_surrogate_paper.json`` (the earlier run: paper MLP and 5 paper MLPs,
early-stopping on the held-out rows) and ``sweep/sweep_h100.json`` (the settings sweep).
The 10,000-row figure extrapolates a power law ``1 - R^2 = a n^-b`` fitted per feature to the sweep's
new-settings ensemble learning curve (250/500/1,000/1,600 rows) to 8,000 training rows (80 % of 10,000).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
BENCH = ROOT / "benchmarks" / "results"
BAR_MEAN, BAR_MIN = 0.95, 0.85


def _load(name: str) -> dict:
    return json.loads((BENCH / name).read_text())


def _power_law(n: np.ndarray, r2: np.ndarray, target: float) -> float:
    """R^2 at ``target`` rows from a least-squares fit of log(1 - R^2) on log n."""
    err = np.clip(1.0 - np.asarray(r2), 1e-6, None)
    b, a = np.polyfit(np.log(n), np.log(err), 1)
    return float(1.0 - np.exp(a + b * np.log(target)))


def main() -> dict:
    mlp, ens = (_load(f"simulator_surrogate_paper_{k}.json") for k in ("mlp", "ensemble"))
    old = _load("simulator_surrogate_paper.json")
    sweep = json.loads((HERE / "sweep" / "sweep_h100.json").read_text())
    names = mlp["feature_names"]
    cfg = sweep["configs"]

    def sweep_row(key: str, which: str) -> dict:
        c = cfg[key]["curve"][-1]
        per = c["ensemble_per_feature"] if which == "ensemble" else c["member_mean_per_feature"]
        return dict(zip(names, per, strict=True))

    columns = {
        "MLP paper, before (ES on held-out)": old["models"]["mlp"]["r2_per_feature"],
        "Ensemble paper, before (ES on held-out)": old["models"]["ensemble"]["r2_per_feature"],
        "MLP paper (ES on train carve)": mlp["models"]["mlp_paper"]["r2_per_feature"],
        "MLP new settings": mlp["models"]["mlp_new"]["r2_per_feature"],
        "Ensemble new = shipped": ens["models"]["ensemble"]["r2_per_feature"],
        "sweep: 5 paper MLPs (H100)": sweep_row("paper", "ensemble"),
        "sweep: 5 new MLPs (H100)": sweep_row("modern_none", "ensemble"),
    }
    peers = {k: dict(zip(names, v["per_feature"], strict=True)) for k, v in sweep["peers"].items()}
    columns.update({f"peer: {k}": v for k, v in peers.items()})

    curves = {"MLP paper (CPU bench)": mlp["learning_curves"]["mlp_paper"],
              "MLP new (CPU bench)": mlp["learning_curves"]["mlp_new"]}
    for key, label in (("paper", "5 paper MLPs"), ("modern_none", "5 new MLPs (600 epochs)")):
        rows = cfg[f"{key}_lc"]["curve"] + cfg[key]["curve"]
        curves[f"sweep: {label} (H100)"] = [
            {"n_train": r["n_train"], "r2": r["ensemble_r2"], "r2_min_feature": min(r["ensemble_per_feature"]),
             "r2_per_feature": dict(zip(names, r["ensemble_per_feature"], strict=True))} for r in rows]
        curves[f"sweep: one {'paper' if key == 'paper' else 'new'} MLP (H100, mean of 5)"] = [
            {"n_train": r["n_train"], "r2": float(np.mean(r["member_r2"])),
             "r2_min_feature": min(r["member_mean_per_feature"])} for r in rows]

    lc = curves["sweep: 5 new MLPs (600 epochs) (H100)"]
    n = np.array([r["n_train"] for r in lc], dtype=float)
    extrap = {f: _power_law(n, np.array([r["r2_per_feature"][f] for r in lc]), 8000) for f in names}
    # the slope of the last two points only (the curve flattens at the end): a more cautious figure
    last = {f: _power_law(n[-2:], np.array([r["r2_per_feature"][f] for r in lc[-2:]]), 8000) for f in names}
    shipped = columns["Ensemble new = shipped"]
    summary = {
        "bar": {"mean": BAR_MEAN, "every_feature": BAR_MIN},
        "shipped": {"surrogate": "ensemble (5 x SkipMLP 256-256-128, SiLU, AdamW, one-cycle 200 epochs)",
                    "r2": float(np.mean(list(shipped.values()))), "r2_min": float(min(shipped.values())),
                    "failing_features": [f for f, v in shipped.items() if v < BAR_MIN]},
        "extrapolated_8000_train_rows": {"r2": float(np.mean(list(extrap.values()))),
                                        "r2_min": float(min(extrap.values())), "per_feature": extrap,
                                        "fit": "all four curve points (250-1,600)"},
        "extrapolated_8000_train_rows_last_slope": {
            "r2": float(np.mean(list(last.values()))), "r2_min": float(min(last.values())), "per_feature": last,
            "fit": "the 1,000 and 1,600 points only"},
    }
    report = {"sources": ["benchmarks/results/simulator_surrogate_paper_mlp.json",
                          "benchmarks/results/simulator_surrogate_paper_ensemble.json",
                          "benchmarks/results/simulator_surrogate_paper.json",
                          "results/orange_peel_paper_surrogate/sweep/sweep_h100.json"],
              "fingerprint": mlp["fingerprint"], "identity": mlp["identity"], "summary": summary,
              "per_feature": columns, "learning_curves": curves}
    (HERE / "surrogate_quality.json").write_text(json.dumps(report, indent=1))
    _markdown(report, names)
    _plot(curves)
    return report


def _markdown(report: dict, names: list[str]) -> None:
    cols = report["per_feature"]
    lines = ["# Orange peel (paper preset): surrogate quality", "",
             "Held-out R^2 (400 rows) in raw feature units; generated by `make_report.py` from "
             + ", ".join(f"`{s}`" for s in report["sources"]) + ".", "",
             "| feature | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    for f in names:
        lines.append(f"| {f} | " + " | ".join(f"{cols[c][f]:.3f}" for c in cols) + " |")
    lines.append("| **mean** | " + " | ".join(f"**{np.mean(list(cols[c].values())):.3f}**" for c in cols) + " |")
    lines.append("| min | " + " | ".join(f"{min(cols[c].values()):.3f}" for c in cols) + " |")
    lines += ["", "## Learning curves (mean R^2 / worst feature)", "",
              "| curve | " + " | ".join(str(r["n_train"]) for r in report["learning_curves"]["MLP paper (CPU bench)"])
              + " |", "|---|" + "---:|" * 4]
    for label, rows in report["learning_curves"].items():
        lines.append(f"| {label} | " + " | ".join(f"{r['r2']:.3f} / {r['r2_min_feature']:.3f}" for r in rows) + " |")
    s = report["summary"]
    lines += ["", f"Shipped ensemble: mean {s['shipped']['r2']:.3f}, worst {s['shipped']['r2_min']:.3f} "
              f"(bar {s['bar']['mean']} / {s['bar']['every_feature']}); below the per-feature bar: "
              + (", ".join(s["shipped"]["failing_features"]) or "none") + ".",
              f"Power-law extrapolation to 8,000 training rows (10,000 runs): mean "
              f"{s['extrapolated_8000_train_rows']['r2']:.3f}, worst {s['extrapolated_8000_train_rows']['r2_min']:.3f} "
              "(power law on all four points of the sweep's new-settings ensemble curve); from the last two "
              f"points' slope only: mean {s['extrapolated_8000_train_rows_last_slope']['r2']:.3f}, worst "
              f"{s['extrapolated_8000_train_rows_last_slope']['r2_min']:.3f}.",
              ""]
    (HERE / "surrogate_quality.md").write_text("\n".join(lines))


def _plot(curves: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for label, rows in curves.items():
        n = [r["n_train"] for r in rows]
        style = "--" if "CPU" in label else "-"
        axes[0].plot(n, [r["r2"] for r in rows], style, marker="o", label=label)
        axes[1].plot(n, [r["r2_min_feature"] for r in rows], style, marker="o", label=label)
    for ax, title, bar in ((axes[0], "mean held-out R^2", BAR_MEAN), (axes[1], "worst feature's R^2", BAR_MIN)):
        ax.axhline(bar, color="k", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.set_xticks([250, 500, 1000, 1600], ["250", "500", "1,000", "1,600"])
        ax.minorticks_off()
        ax.set_xlabel("training rows")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(HERE / "learning_curve.png", dpi=110)
    fig.savefig(ROOT / "docs" / "orange-peel" / "surrogate_learning_curve.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
