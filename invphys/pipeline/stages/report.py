"""The ``report`` stage: tables, a plot and renders from the invert and validate stages.

Writes under ``OUT/report/`` (formats from ``report.formats``):

* ``report.md``: a summary table per optimiser (mean R_surr, R_actual, Delta, evaluations, time, failed
  runs), one table per target (evaluations, R_surr, R_actual, Delta, time), the named objectives,
  and the plot and renders embedded;
* ``report.csv`` / ``report.json``: every (optimiser, problem) row with its validation numbers;
* ``recovery.png``: mean R_surr vs R_actual per optimiser (targets) and best-so-far R against
  evaluations (log scale);
* ``renders/tNN.png``: the target's and the recovered run's final states side by side, each drawn by
  the simulator's :meth:`~invphys.core.interfaces.Simulator.render` with ``max_frames=1`` (runs with
  particle frames, or a simulator with its own renderer);
* ``renders/tNN_series.png``: the target's and the recovered run's time series overlaid, one panel per
  series they share.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("report", "targets")


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "n/a"
        if v.is_integer() and abs(v) >= 1:  # counts such as mean evaluations
            return f"{int(v):,}"
        return f"{v:.{digits}f}"
    return str(v)


def _merge(rows: list[dict[str, Any]], validation: list[dict[str, Any]] | None) -> list[dict[str, Any]]:
    key = ("optimizer", "problem", "problem_id")
    val = {tuple(v[k] for k in key): v for v in validation or []}
    merged = []
    for r in rows:
        v = val.get(tuple(r[k] for k in key))
        merged.append({
            "optimizer": r["optimizer"], "type": r["type"], "space": r["space"], "evaluator": r["evaluator"],
            "problem": r["problem"], "problem_id": r["problem_id"], "target_index": r["target_index"],
            "evaluations": r["evaluations"], "wall_time_s": r["wall_time_s"],
            "r_surrogate": v["r_surrogate"] if v else r["r_surrogate"],
            "r_actual": v["r_actual"] if v else None, "gap": v["gap"] if v else None,
            "failure": v["failure"] if v else None, "sim_time_s": v.get("sim_time_s") if v else None,
            "validated": v is not None, "params": r["params"], "history": r["history"]})
    return merged


def _mean(vals: list[Any]) -> float | None:
    a = np.array([v for v in vals if v is not None], dtype=np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else None


def summary_table(merged: list[dict[str, Any]], problem: str = "target") -> list[dict[str, Any]]:
    """One row per optimiser: means over its problems of the given kind (validated ones for R_actual)."""
    out = []
    for label in dict.fromkeys(r["optimizer"] for r in merged):
        sel = [r for r in merged if r["optimizer"] == label and r["problem"] == problem]
        if not sel:
            continue
        val = [r for r in sel if r["validated"]]
        out.append({"optimizer": label, "type": sel[0]["type"], "space": sel[0]["space"],
                    "evaluator": sel[0]["evaluator"], "n": len(sel), "validated": len(val),
                    "evaluations": _mean([r["evaluations"] for r in sel]),
                    "r_surrogate": _mean([r["r_surrogate"] for r in sel]),
                    "r_surrogate_validated": _mean([r["r_surrogate"] for r in val]),
                    "r_actual": _mean([r["r_actual"] for r in val]), "gap": _mean([r["gap"] for r in val]),
                    "time_s": _mean([r["wall_time_s"] for r in sel]),
                    "failed": sum(1 for r in val if r["failure"])})
    return out


def _md_table(header: list[str], rows: list[list[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(_fmt(c) for c in row) + " |" for row in rows]
    return lines


def markdown(ctx_name: str, merged: list[dict[str, Any]], targets: dict[str, Any], plot: str | None,
             renders: list[tuple[int, str, str]]) -> str:
    lines = [f"# Inverse recovery report: {ctx_name}", ""]
    n_t = len(targets["rows"])
    lines += [f"{n_t} held-out targets ({targets['selection']} selection from the test partition), the first "
              f"{targets['validate']} re-run through the simulator. R = R_gt (paper eq. 1); R_surr on the "
              f"optimiser's evaluator, R_actual from the simulator, Delta = R_surr - R_actual "
              f"(over validated targets).", ""]
    summ = summary_table(merged, "target")
    if summ:
        lines += ["## Summary (targets)", ""]
        lines += _md_table(["optimizer", "type", "space", "evaluator", "evaluations", "R_surr (all)",
                            "R_surr (validated)", "R_actual", "Delta", "time (s)", "failed"],
                           [[s["optimizer"], s["type"], s["space"], s["evaluator"], s["evaluations"],
                             s["r_surrogate"], s["r_surrogate_validated"], s["r_actual"], s["gap"], s["time_s"],
                             f"{s['failed']}/{s['validated']}"] for s in summ])
        lines.append("")
    if plot:
        lines += [f"![recovery]({plot})", ""]
    ks = sorted({r["target_index"] for r in merged if r["problem"] == "target"})
    if ks:
        lines += ["## Per target", ""]
    for k in ks:
        sel = [r for r in merged if r["problem"] == "target" and r["target_index"] == k]
        lines += [f"### Target {k} (dataset row {targets['rows'][k]})", ""]
        lines += _md_table(["optimizer", "evaluations", "R_surr", "R_actual", "Delta", "time (s)", "note"],
                           [[r["optimizer"], r["evaluations"], r["r_surrogate"], r["r_actual"], r["gap"],
                             r["wall_time_s"], r["failure"] or ("" if r["validated"] else "not validated")]
                            for r in sel])
        for kk, path, caption in renders:
            if kk == k:
                lines += ["", f"![target {k}: {caption}]({path})"]
        lines.append("")
    objs = sorted({r["problem_id"] for r in merged if r["problem"] == "objective"})
    if objs:
        lines += ["## Named objectives", "", "Score = the weighted objective (higher is better).", ""]
        lines += _md_table(["objective", "optimizer", "evaluations", "score (surrogate)", "score (simulator)",
                            "Delta", "time (s)"],
                           [[r["problem_id"], r["optimizer"], r["evaluations"], r["r_surrogate"], r["r_actual"],
                             r["gap"], r["wall_time_s"]]
                            for o in objs for r in merged if r["problem"] == "objective" and r["problem_id"] == o])
        lines.append("")
    return "\n".join(lines)


def plot_recovery(merged: list[dict[str, Any]], path: Path) -> Path | None:
    """Bar chart of mean R_surr / R_actual per optimiser and best-so-far curves; None without targets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summ = summary_table(merged, "target")
    if not summ:
        return None
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    x = np.arange(len(summ))
    surr = [s["r_surrogate_validated"] if s["r_surrogate_validated"] is not None else s["r_surrogate"] for s in summ]
    act = [s["r_actual"] if s["r_actual"] is not None else np.nan for s in summ]
    ax1.bar(x - 0.2, surr, 0.4, label="R_surr")
    ax1.bar(x + 0.2, act, 0.4, label="R_actual (simulator)")
    ax1.set_xticks(x, [s["optimizer"] for s in summ], rotation=30, ha="right")
    ax1.set_ylim(0, 1)
    ax1.set_ylabel("mean recovery R_gt")
    ax1.legend(fontsize=8)
    for s in summ:
        curves = [np.array(r["history"], dtype=np.float64) for r in merged
                  if r["optimizer"] == s["optimizer"] and r["problem"] == "target" and r["history"]]
        if not curves:
            continue
        grid = np.unique(np.concatenate([c[:, 0] for c in curves]))
        vals = np.array([np.interp(grid, c[:, 0], np.maximum.accumulate(c[:, 1])) for c in curves])
        ax2.plot(grid, vals.mean(axis=0), label=s["optimizer"], marker="." if len(grid) < 20 else None)
    ax2.set_xscale("log")
    ax2.set_xlabel("surrogate evaluations")
    ax2.set_ylabel("best-so-far R_surr (mean over targets)")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def render_final_state(simulator: Any, traj: Any, path: Path, title: str) -> Path | None:
    """Draw a trajectory's final state to the PNG ``path`` with ``simulator.render(..., max_frames=1)``
    (the generic renderer when ``simulator`` is None); None when there is nothing to draw (a run without
    particles whose simulator has no renderer of its own: its series are plotted instead)."""
    from invphys.core.interfaces import Simulator
    from invphys.core.trajectory_plot import render_trajectory

    own = simulator is not None and type(simulator).render is not Simulator.render
    if not (own or traj.has_particles):
        return None
    tmp = path.parent / f".{path.stem}.tmp"
    try:
        if own:
            done = simulator.render(traj, tmp, max_frames=1, animation="none")
        else:
            done = render_trajectory(traj, tmp, max_frames=1, animation="none", title=title)
        if not done.images:
            return None
        shutil.copyfile(done.images[0], path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def side_by_side(left: Path, right: Path, path: Path, titles: tuple[str, str]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, img, title in zip(axes, (left, right), titles, strict=True):
        ax.imshow(mpimg.imread(img))
        ax.set_title(title, fontsize=10)
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _renders(ctx: StageContext, out_dir: Path) -> list[tuple[int, str, str]]:
    from invphys.core.trajectory_io import load_trajectory
    from invphys.core.trajectory_plot import plot_series

    src = ctx.stage_dir_of("validate") / "renders"
    if not ctx.spec.report.render or not src.is_dir():
        return []
    try:
        simulator = ctx.simulator()
    except Exception:  # a simulator that cannot be built here still gets the generic renderer
        simulator = None
    done: list[tuple[int, str, str]] = []
    for tgt in sorted(src.glob("t*_target.npz")):
        k = int(tgt.name[1:3])
        rec = src / f"t{k:02d}_recovered.npz"
        if not rec.is_file():
            continue
        d = out_dir / "renders"
        d.mkdir(parents=True, exist_ok=True)
        target, recovered = load_trajectory(tgt), load_trajectory(rec)
        a = render_final_state(simulator, target, d / f"t{k:02d}_target_frame.png", f"target {k}")
        b = render_final_state(simulator, recovered, d / f"t{k:02d}_recovered_frame.png", f"recovered {k}")
        if a is not None and b is not None:
            side_by_side(a, b, d / f"t{k:02d}.png", (f"target {k} (ground-truth parameters)",
                                                     "recovered (best validated optimiser)"))
            done.append((k, f"renders/t{k:02d}.png", "target vs recovered"))
        if plot_series({"target": target, "recovered": recovered}, d / f"t{k:02d}_series.png",
                       title=f"target {k}: time series") is not None:
            done.append((k, f"renders/t{k:02d}_series.png", "time series, target vs recovered"))
    return done


def run(ctx: StageContext) -> dict[str, Any]:
    import pandas as pd

    from invphys.core.atomic import write_json
    from invphys.pipeline.stages.invert import load_results
    from invphys.pipeline.stages.validate import load_validation

    rows, targets = load_results(ctx)
    validation = load_validation(ctx)
    merged = _merge(rows, validation)
    out = ctx.stage_dir
    plot = plot_recovery(merged, out / "recovery.png")
    renders = _renders(ctx, out)
    formats = set(ctx.spec.report.formats)
    flat = [{k: v for k, v in r.items() if k not in ("params", "history")}
            | {f"param_{k}": v for k, v in r["params"].items()} for r in merged]
    files = []
    if "md" in formats:
        (out / "report.md").write_text(markdown(ctx.spec.name, merged, targets,
                                                plot.name if plot else None, renders))
        files.append("report.md")
    if "csv" in formats:
        pd.DataFrame(flat).to_csv(out / "report.csv", index=False)
        files.append("report.csv")
    summ = summary_table(merged, "target")
    if "json" in formats:
        write_json(out / "report.json", {"summary": summ, "objectives": summary_table(merged, "objective"),
                                         "rows": flat, "targets": targets})
        files.append("report.json")
    ctx.log(f"wrote {', '.join(files)} to {out}")
    return {"files": files, "plot": plot.name if plot else None, "renders": [p for _, p, _ in renders],
            "summary": summ}
