"""R_actual per method with bootstrap intervals, and the paired differences against the reference."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def plot_protocol(summary: dict[str, dict[str, Any]], path: Path, reference: str = "nearest_neighbour",
                  title: str = "") -> Path | None:
    """Two panels: mean R_actual with its 95 % interval per method, and the paired difference against
    ``reference`` with its interval (a method beats the reference when the interval is right of 0).
    None when no method has a validated R_actual."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    items = [(lab, s) for lab, s in summary.items() if s.get("r_actual_mean") is not None]
    if not items:
        return None
    items.sort(key=lambda x: x[1]["r_actual_mean"])
    colours = {"baseline": "C1", "reference": "tab:gray", "method": "tab:green"}
    key = f"vs_{reference}"
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 0.9 + 0.38 * len(items)), sharey=True)
    ypos = np.arange(len(items))
    for y, (_lab, s) in zip(ypos, items, strict=True):
        c = colours.get(s.get("role") or "", "tab:blue")
        lo, hi = s["r_actual_ci95"]
        m = s["r_actual_mean"]
        ax1.errorbar(m, y, xerr=[[m - lo], [hi - m]], fmt="o", color=c, capsize=3)
        d = s.get(key)
        if d and d.get("mean_diff") is not None:
            dlo, dhi = d["ci95"]
            ax2.errorbar(d["mean_diff"], y, xerr=[[d["mean_diff"] - dlo], [dhi - d["mean_diff"]]], fmt="o",
                         color="tab:green" if d.get("beats") else c, capsize=3)
    if reference in summary and summary[reference].get("r_actual_mean") is not None:
        ax1.axvline(summary[reference]["r_actual_mean"], color="C1", ls=":", lw=1)
    ax1.set_yticks(ypos, [f"{lab} (n={s['n_validated']})" for lab, s in items])
    ax1.set_xlabel("mean R_actual (simulator), 95 % bootstrap interval")
    ax1.set_xlim(0, 1.02)
    ax2.axvline(0.0, color="k", lw=1)
    ax2.set_xlabel(f"paired difference vs {reference} (green: interval above 0)")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
