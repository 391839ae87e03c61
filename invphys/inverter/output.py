"""Files an answer can be written to: its draws (``.npz``/``.csv``), a table row per target (``.csv``)
and a corner-style pairplot of the draws with the answer marked."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.inverter.result import InversionResult


def check_new_file(path: str | Path, what: str, suffixes: Sequence[str]) -> Path:
    """``path`` as a new file to write (never an existing one, its folder an existing folder), or an
    :class:`InvphysError` naming it; checked before any answer is computed."""
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise InvphysError(f"{what} {p}: name a {' or '.join(suffixes)} file")
    if p.exists() or p.is_symlink():
        raise InvphysError(f"{what} {p} exists; name a new file (invphys does not overwrite it)")
    if not p.absolute().parent.is_dir():
        raise InvphysError(f"{what} {p}: its folder {p.absolute().parent} is not an existing directory")
    return p


def _draws(results: Sequence[InversionResult], n: int) -> np.ndarray:
    """(B, n, d) physical draws of every result (each must hold at least n)."""
    out = []
    for r in results:
        u = r.parameter_uncertainty
        if u.draws is None or len(u.draws) < n:
            raise InvphysError(f"target {r.label}: method {r.method!r} has no posterior draws to save "
                               f"(posterior: {u.kind})")
        out.append(r._physical(u.draws[:n]))
    return np.stack(out)


def write_samples(results: Sequence[InversionResult], n: int, path: str | Path) -> Path:
    """The first ``n`` draws of each result in physical units: ``.npz`` (``samples`` (B, n, d),
    ``theta`` normalised, ``parameter_names``, ``units``, ``targets``) or long ``.csv`` (target, draw,
    one column per parameter)."""
    p = Path(path)
    phys = _draws(results, n)
    names = list(results[0].parameter_names)
    if p.suffix.lower() == ".npz":
        theta = np.stack([r.parameter_uncertainty.draws[:n] for r in results])  # type: ignore[index]
        with open(p, "xb") as fh:
            np.savez(fh, samples=phys, theta=theta, parameter_names=np.array(names),
                     units=np.array(list(results[0].parameter_units)), targets=np.array([r.label for r in results]))
        return p
    with open(p, "x", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["target", "draw", *names])
        for r, rows in zip(results, phys, strict=True):
            for j, row in enumerate(rows):
                w.writerow([r.label, j, *(f"{v:.9g}" for v in row)])
    return p


def table_rows(results: Sequence[InversionResult]) -> list[dict[str, Any]]:
    """One flat row per target: the answer, and per parameter its interval and identifiability."""
    rows = []
    for r in results:
        row: dict[str, Any] = {"target": r.label, "method": r.method, "posterior": r.posterior,
                               "r_surrogate": r.r_surrogate, "r_actual": r.r_actual}
        iv = r.interval() if r.parameter_uncertainty.has_draws else {}
        ident = r.identified or {}
        for name, value in r.parameters.items():
            row[name] = value
            if name in iv:
                row[f"{name}_low"], row[f"{name}_median"], row[f"{name}_high"] = iv[name]
            if name in ident:
                row[f"{name}_identified"] = ident[name]
        if r.target_std is not None:
            row["noise"] = " ".join(f"{n}={s:.6g}" for n, s, g in zip(r.feature_names, r.target_std, r.mask, strict=True)
                                    if g and np.isfinite(s) and s > 0)
            row["chi2"] = r.chi2()
        row["at_bound"] = " ".join(r.at_bound)
        row["warnings"] = " | ".join(r.warnings)
        rows.append(row)
    return rows


def write_table(results: Sequence[InversionResult], path: str | Path) -> Path:
    rows = table_rows(results)
    keys = list(dict.fromkeys(k for row in rows for k in row))
    with open(path, "x", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    return Path(path)


def pairplot(result: InversionResult, path: str | Path) -> Path:
    """Corner-style pairplot of one result's draws (parameter order, physical units, log10 of the
    log-scaled parameters), the answer marked in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    u = result.parameter_uncertainty
    if u.draws is None or not len(u.draws):
        raise InvphysError(f"target {result.label}: method {result.method!r} has no draws to plot "
                           f"(posterior: {u.kind})")
    x = result._physical(u.draws)
    best = np.asarray(result.best.params, dtype=np.float64)
    names, d = result.parameter_names, len(result.parameter_names)
    logs = [bool(getattr(p, "log", False)) for p in result.space.parameters]
    x = np.where(logs, np.log10(np.maximum(x, 1e-300)), x)
    best = np.where(logs, np.log10(np.maximum(best, 1e-300)), best)
    labels = [f"log10 {n}" if lg else n for n, lg in zip(names, logs, strict=True)]
    fig, axes = plt.subplots(d, d, figsize=(1.6 * d, 1.6 * d), squeeze=False)
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(x[:, i], bins=30, color="0.5")
                ax.axvline(best[i], color="red")
                ax.set_yticks([])
            else:
                ax.scatter(x[:, j], x[:, i], s=2, color="0.3", alpha=0.4, linewidths=0)
                ax.scatter([best[j]], [best[i]], s=25, color="red", marker="x")
            ax.tick_params(labelsize=5)
            if i == d - 1:
                ax.set_xlabel(labels[j], fontsize=7)
            if j == 0 and i > 0:
                ax.set_ylabel(labels[i], fontsize=7)
    fig.suptitle(f"target {result.label}: {u.kind} draws ({len(x)}), answer in red", fontsize=8)
    fig.tight_layout()
    with open(path, "xb") as fh:
        fig.savefig(fh, dpi=110, format=Path(path).suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    return Path(path)
