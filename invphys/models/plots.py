"""Training-curve and parity plots of the learned models (matplotlib, Agg backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_curves(history: dict[str, Any], path: str | Path, title: str) -> Path:
    """Train/validation loss per epoch (log scale), plus the loss parts; ensembles: one line per member."""
    plt = _pyplot()
    histories = history.get("members") or [history]
    parts = {} if "members" in history else history.get("parts", {})
    ncols = 2 if parts else 1
    fig, axes = plt.subplots(1, ncols, figsize=(5.5 * ncols, 3.8), squeeze=False)
    ax = axes[0, 0]
    for i, h in enumerate(histories):
        sfx = f" #{i + 1}" if len(histories) > 1 else ""
        ax.plot(h.get("train_loss", []), lw=1, label=f"train{sfx}")
        ax.plot(h.get("val_loss", []), lw=1, ls="--", label=f"validation{sfx}")
        if "best_epoch" in h and h.get("val_loss"):
            ax.axvline(h["best_epoch"], color="grey", lw=0.6, alpha=0.5)
    losses = [v for h in histories for key in ("train_loss", "val_loss") for v in h.get(key, [])]
    if losses and min(losses) > 0:  # a flow's NLL can make the total negative: keep a linear axis then
        ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.legend(fontsize=7, ncol=2 if len(histories) > 1 else 1)
    if parts:
        ax2 = axes[0, 1]
        for k, v in parts.items():
            ax2.plot(np.asarray(v, dtype=float), lw=1, label=k)
        if all(np.all(np.asarray(v, dtype=float) > 0) for v in parts.values()):
            ax2.set_yscale("log")
        ax2.set_xlabel("epoch")
        ax2.set_title("validation loss parts")
        ax2.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_parity(y_true: np.ndarray, y_pred: np.ndarray, names: Sequence[str], path: str | Path,
                title: str) -> Path:
    """Predicted against true value, one panel per feature, with each panel's R^2."""
    from invphys.models.data import r2_scores

    plt = _pyplot()
    m = y_true.shape[1]
    ncols = min(4, m)
    nrows = int(np.ceil(m / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.0 * ncols, 2.8 * nrows), squeeze=False)
    _, per = r2_scores(y_true, y_pred)
    for j in range(nrows * ncols):
        ax = axes[j // ncols, j % ncols]
        if j >= m:
            ax.axis("off")
            continue
        ax.scatter(y_true[:, j], y_pred[:, j], s=5, alpha=0.6)
        lo = float(min(y_true[:, j].min(), y_pred[:, j].min()))
        hi = float(max(y_true[:, j].max(), y_pred[:, j].max()))
        ax.plot([lo, hi], [lo, hi], color="k", lw=0.6)
        ax.set_title(f"{names[j]}\nR²={per[j]:.3f}", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
