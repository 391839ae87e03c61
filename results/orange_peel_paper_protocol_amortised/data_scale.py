"""Recovery against training rows on the same 100 targets (issue 17 item 6), from the committed runs.

Every run below answers the same 100 held-out targets of `datasets/orange_peel_paper`, scored with the same
scales (checked: the script stops if a run's targets or scales differ); every answer was re-simulated on a
GPU. Paired bootstrap intervals (2,000 resamples over targets) compare each answer with the lookup in the
same run, and each answer across runs that differ only in training rows (same ensemble size).
usage: python results/orange_peel_paper_protocol_amortised/data_scale.py   ->  data_scale.json, data_scale.png
"""
from __future__ import annotations

import json
import tarfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
#: label -> (archive with invert/targets.json and validate/validation.json, training rows, ensemble members)
RUNS = {
    "1600_m3": (HERE / "v030" / "run.tgz", 1600, 3),
    "2624_m3": (HERE / "v030_extra2" / "run.tgz", 2624, 3),
    "1600_m5": (HERE.parent / "orange_peel_paper_protocol_v030" / "validate.tgz", 1600, 5),
    "3776_m5": (HERE / "v030_extra3" / "run.tgz", 3776, 5),
    "8256_m5": (HERE / "v030_8k" / "run.tgz", 8256, 5),
    "9600_m5": (HERE / "v030_10k" / "run.tgz", 9600, 5),   # 10,000 runs with the 400 held-out rows
}
#: more rows against fewer, same ensemble size; "9600_m5-1600_m5" is issue 17's 10,000 against 2,000 runs
PAIRS = [("2624_m3", "1600_m3"), ("3776_m5", "1600_m5"), ("8256_m5", "3776_m5"), ("9600_m5", "8256_m5"),
         ("9600_m5", "1600_m5")]
ANSWERS = ["nearest_neighbour", "npe_surrogate", "npe_penalised", "corrected_search", "cma_penalised_nn_64"]
LOOKUP = "nearest_neighbour"


def _read(tgz: Path, member: str) -> object:
    with tarfile.open(tgz) as tar:
        return json.load(tar.extractfile(member))


def paired(a: np.ndarray, b: np.ndarray, rng: np.random.Generator, n: int = 2000) -> list[float]:
    """[mean, 2.5 %, 97.5 %] of the bootstrap mean of a - b over targets."""
    d = a - b
    boots = d[rng.integers(0, len(d), size=(n, len(d)))].mean(1)
    return [round(float(d.mean()), 4), round(float(np.percentile(boots, 2.5)), 4),
            round(float(np.percentile(boots, 97.5)), 4)]


def mean_ci(a: np.ndarray, rng: np.random.Generator, n: int = 2000) -> list[float]:
    """[mean, 2.5 %, 97.5 %] of the bootstrap mean of ``a`` over targets."""
    boots = a[rng.integers(0, len(a), size=(n, len(a)))].mean(1)
    return [round(float(a.mean()), 4), round(float(np.percentile(boots, 2.5)), 4),
            round(float(np.percentile(boots, 97.5)), 4)]


def plot(out: dict, path: Path) -> None:
    """R_actual (mean, 95 % interval) against training rows, one line per answer and ensemble size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for members, style in ((3, "--"), (5, "-")):
        runs = sorted((v["training_rows"], k) for k, v in out["runs"].items() if v["ensemble_members"] == members)
        for answer, colour in (("nearest_neighbour", "tab:gray"), ("npe_surrogate", "tab:blue"),
                               ("npe_penalised", "tab:green"), ("corrected_search", "tab:orange")):
            pts = [(rows, out["mean_R_actual_ci"][k][answer]) for rows, k in runs if answer in out["mean_R_actual_ci"][k]]
            if len(pts) < 2:
                continue
            x = np.array([p[0] for p in pts])
            m, lo, hi = (np.array([p[1][j] for p in pts]) for j in range(3))
            ax.errorbar(x, m, yerr=[m - lo, hi - m], fmt="o" + style, color=colour, capsize=3,
                        label=f"{answer} ({members}-member ensemble)")
    ax.set_xticks([1600, 2624, 3776, 8256, 9600], ["1,600", "2,624", "3,776", "8,256", "9,600"])
    ax.set_xlabel("training rows (same 100 held-out targets)")
    ax.set_ylabel("mean R_actual (simulator), 95 % interval")
    ax.set_title("Amortised answers against the lookup as data grows")
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def r_actual(tgz: Path, n: int) -> dict[str, np.ndarray]:
    """Per-target R_actual of every answer in ANSWERS that the run validated (a failed run scores 0)."""
    by: dict[str, dict[int, float]] = {}
    for row in _read(tgz, "validate/validation.json"):
        if row["problem"] == "target" and row["optimizer"] in ANSWERS:
            by.setdefault(row["optimizer"], {})[row["target_index"]] = row.get("r_actual") or 0.0
    return {m: np.array([v[i] for i in range(n)]) for m, v in by.items() if len(v) >= n}


def main() -> None:
    targets = {k: _read(p, "invert/targets.json") for k, (p, _, _) in RUNS.items()}
    first = next(iter(targets.values()))
    for k, t in targets.items():
        if t["rows"] != first["rows"] or t["scales"] != first["scales"]:
            raise SystemExit(f"run {k} does not share the targets and scales of the others")
    n = len(first["rows"])
    r = {k: r_actual(p, n) for k, (p, _, _) in RUNS.items()}
    rng = np.random.default_rng(0)
    out = {
        "targets": n,
        "runs": {k: {"archive": str(p.relative_to(HERE.parent)), "training_rows": rows, "ensemble_members": m}
                 for k, (p, rows, m) in RUNS.items()},
        "mean_R_actual": {k: {m: round(float(v.mean()), 4) for m, v in r[k].items()} for k in RUNS},
        "mean_R_actual_ci": {k: {m: mean_ci(v, np.random.default_rng(1)) for m, v in r[k].items()} for k in RUNS},
        "vs_nearest_neighbour": {k: {m: paired(v, r[k][LOOKUP], rng) for m, v in r[k].items() if m != LOOKUP}
                                 for k in RUNS},
        "more_rows_minus_fewer": {f"{a}-{b}": {m: paired(r[a][m], r[b][m], rng) for m in r[a] if m in r[b]}
                                  for a, b in PAIRS},
        "note": "[mean, 2.5 %, 97.5 %] of paired differences over targets; a failed run scores 0",
    }
    (HERE / "data_scale.json").write_text(json.dumps(out, indent=2) + "\n")
    plot(out, HERE / "data_scale.png")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
