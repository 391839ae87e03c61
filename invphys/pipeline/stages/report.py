"""The ``report`` stage: tables, a plot and renders from the invert and validate stages.

Writes under ``OUT/report/`` (formats from ``report.formats``):

* ``report.md``: a summary table per optimiser (mean R_surr, R_actual, Delta, evaluations, time, failed
  runs), one table per target (evaluations, R_surr, R_actual, Delta, time), the named objectives,
  and the plot and renders embedded;
* ``report.csv`` / ``report.json``: every (optimiser, problem) row with its validation numbers;
* ``recovery.png``: mean R_surr vs R_actual per optimiser (targets) and best-so-far R against
  evaluations (log scale);
* ``protocol.png``: mean R_actual per method with bootstrap 95 % intervals, and the paired differences
  against the nearest-neighbour baseline (the evaluation protocol, docs/evaluation.md);
* ``report.json`` also holds ``optimizers`` (per label, baselines included: ``n_validated``,
  ``r_actual_mean``, ``r_actual_ci95``, ``r_surrogate_mean``, ``gap_mean``, ``evaluations``,
  ``simulator_runs``, ``wall_time_s``, ``device``, ``vs_nearest_neighbour``), ``parameters`` (recovered
  parameters per target and method, errors, identifiability) and ``uncertainty`` (the ensemble check);
* ``renders/tNN.png``: the target's and the recovered run's final states side by side, each drawn by
  the simulator's :meth:`~invphys.core.interfaces.Simulator.render` with ``max_frames=1`` (runs with
  particle frames, or a simulator with its own renderer);
* ``renders/tNN_series.png``: the target's and the recovered run's time series overlaid, one panel per
  series they share.

Parameters are listed in the parameter space's order everywhere (report.csv's ``param_*`` columns,
report.json's rows). A drawing or figure that fails (a simulator's ``render`` that raises, a plot that
cannot be made) never fails the stage: it is a warning, logged and listed in report.md (``Warnings``)
and report.json (``warnings``), and the rest of the report is written. report.md says which targets are
drawn when not all of them are.
"""

from __future__ import annotations

import logging
import math
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("report", "targets", "evaluation")


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
            "validated": v is not None, "params": r["params"], "history": r["history"],
            "role": r.get("role", "optimizer"), "simulator_runs": r.get("simulator_runs", 0),
            "simulator_time_s": r.get("simulator_time_s"), "device": r.get("device"), "theta": r.get("theta"), "spread": r.get("spread")})
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
             renders: list[tuple[int, str, str]], protocol: dict[str, Any] | None = None,
             protocol_plot: str | None = None, warnings: list[str] | None = None,
             drawn: str | None = None) -> str:
    lines = [f"# Inverse recovery report: {ctx_name}", ""]
    n_t = len(targets["rows"])
    n_v = len({r["target_index"] for r in merged if r["problem"] == "target" and r["validated"]})
    lines += [f"{n_t} held-out targets ({targets['selection']} selection from the test partition), "
              f"{n_v} of them re-run through the simulator. R = R_gt (paper eq. 1); R_surr on the "
              f"optimiser's evaluator (for baselines, the shared surrogate's score of the answer, even where "
              f"the lookup chose it by a stored row), R_actual from the simulator, Delta = R_surr - R_actual "
              f"(over validated targets).", ""]
    if drawn:
        lines += [drawn, ""]
    if warnings:
        lines += ["## Warnings", "", "Parts of this report that could not be made (the results above and below "
                  "are complete):", "", *[f"- {w}" for w in warnings], ""]
    summ = summary_table(merged, "target")
    if summ:
        lines += ["## Summary (targets)", ""]
        lines += _md_table(["optimizer", "type", "space", "evaluator", "evaluations", "R_surr (all)",
                            "R_surr (validated)", "R_actual", "Delta", "time (s)", "failed"],
                           [[s["optimizer"], s["type"], s["space"], s["evaluator"], _count(s["evaluations"]),
                             s["r_surrogate"], s["r_surrogate_validated"], s["r_actual"], s["gap"], s["time_s"],
                             f"{s['failed']}/{s['validated']}"] for s in summ])
        lines.append("")
    if plot:
        lines += [f"![recovery]({plot})", ""]
    if protocol is not None:
        lines += [*protocol_markdown(protocol, protocol_plot), ""]
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
    """Mean R_surr / R_actual per optimiser and best-so-far curves, as a PNG; None without targets."""
    import matplotlib.pyplot as plt

    fig = recovery_figure(merged)
    if fig is None:
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def recovery_figure(merged: list[dict[str, Any]]) -> Any:
    """The figure of :func:`plot_recovery` (None without targets): horizontal bars, so that method names
    of any length and number never overlap (the figure grows with them), and the best-so-far curves on a
    log axis labelled at 1, 2 and 5 per decade only."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    summ = summary_table(merged, "target")
    if not summ:
        return None
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, max(4.0, 1.5 + 0.45 * len(summ))),
                                   gridspec_kw={"width_ratios": [1, 1.2]})
    y = np.arange(len(summ))[::-1]   # the first method on top
    surr = [s["r_surrogate_validated"] if s["r_surrogate_validated"] is not None else s["r_surrogate"] for s in summ]
    act = [s["r_actual"] if s["r_actual"] is not None else np.nan for s in summ]
    ax1.barh(y + 0.2, [np.nan if v is None else v for v in surr], 0.4, label="R_surr")
    ax1.barh(y - 0.2, act, 0.4, label="R_actual (simulator)")
    ax1.set_yticks(y, [s["optimizer"] for s in summ])
    ax1.set_xlim(0, 1)
    ax1.set_xlabel("mean recovery R_gt")
    ax1.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, frameon=False)
    for s in summ:
        curves = [np.array(r["history"], dtype=np.float64) for r in merged
                  if r["optimizer"] == s["optimizer"] and r["problem"] == "target" and r["history"]]
        if not curves:
            continue
        grid = np.unique(np.concatenate([c[:, 0] for c in curves]))
        vals = np.array([np.interp(grid, c[:, 0], np.maximum.accumulate(c[:, 1])) for c in curves])
        ax2.plot(grid, vals.mean(axis=0), label=s["optimizer"], marker="." if len(grid) < 20 else None)
    if ax2.lines:
        ax2.set_xscale("log")
        lo, hi = ax2.get_xlim()
        decades = np.log10(max(hi, 1.0)) - np.log10(max(lo, 1.0))
        ax2.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0) if decades <= 2 else (1.0,)))
        ax2.xaxis.set_major_formatter(FuncFormatter(lambda x, _: _count_label(x)))
        ax2.xaxis.set_minor_formatter(NullFormatter())
        ax2.legend(fontsize=8)
    else:  # answers without an optimisation history (baselines, simulator-checked answers)
        ax2.text(0.5, 0.5, "no optimiser histories", ha="center", va="center", transform=ax2.transAxes)
    ax2.set_xlabel("surrogate evaluations")
    ax2.set_ylabel("best-so-far R_surr\n(mean over targets)")
    fig.tight_layout()
    return fig


def _count_label(x: float) -> str:
    """A short tick label for a count: 20, 500, 2k, 100k, 3M."""
    for div, suffix in ((1e6, "M"), (1e3, "k")):
        if x >= div:
            return f"{x / div:g}{suffix}"
    return f"{x:g}"


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


def _renders(ctx: StageContext, out_dir: Path, warnings: list[str]) -> list[tuple[int, str, str]]:
    """The target-vs-recovered drawings of the targets the validate stage kept runs of; a drawing that
    fails (a simulator's ``render`` that raises, a trajectory file that cannot be read) is a warning."""
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
        try:
            target, recovered = load_trajectory(tgt), load_trajectory(rec)
        except Exception as exc:
            warnings.append(f"target {k}: not drawn: its runs' files cannot be read ({_why(exc)})")
            continue
        try:
            a = render_final_state(simulator, target, d / f"t{k:02d}_target_frame.png", f"target {k}")
            b = render_final_state(simulator, recovered, d / f"t{k:02d}_recovered_frame.png", f"recovered {k}")
            if a is not None and b is not None:
                side_by_side(a, b, d / f"t{k:02d}.png", (f"target {k} (ground-truth parameters)",
                                                         "recovered (best validated optimiser)"))
                done.append((k, f"renders/t{k:02d}.png", "target vs recovered"))
        except Exception as exc:  # a plugin's renderer: its failure must not sink a finished run
            who = f"the render of simulator {simulator.name!r}" if simulator is not None else "the drawing"
            warnings.append(f"target {k}: final states not drawn: {who} failed ({_why(exc)})")
        try:
            if plot_series({"target": target, "recovered": recovered}, d / f"t{k:02d}_series.png",
                           title=f"target {k}: time series") is not None:
                done.append((k, f"renders/t{k:02d}_series.png", "time series, target vs recovered"))
        except Exception as exc:
            warnings.append(f"target {k}: time series not drawn ({_why(exc)})")
    return done


def _why(exc: BaseException) -> str:
    """One line naming an exception (for a report's warnings)."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    return text if len(text) <= 300 else text[:297] + "..."


def _figure(warnings: list[str], name: str, draw: Any, *args: Any, **kwargs: Any) -> Any:
    """``draw(*args, **kwargs)``, or None and a warning when it fails (a figure never sinks a report)."""
    try:
        return draw(*args, **kwargs)
    except Exception as exc:
        warnings.append(f"{name} not drawn ({_why(exc)})")
        return None


def run(ctx: StageContext) -> dict[str, Any]:
    import pandas as pd

    from invphys.core.atomic import write_json
    from invphys.evaluation.plots import plot_protocol
    from invphys.pipeline.stage_files import load_active, load_results, load_validation

    rows, targets = load_results(ctx)
    validation = load_validation(ctx)
    active_rows, active_val, rounds = load_active(ctx)
    rows = _with_device(ctx, rows) + _evaluation_rows(ctx, targets) + active_rows
    validation = (validation or []) + active_val if (validation or active_val) else None
    merged = _merge(rows, validation)
    out = ctx.stage_dir
    warnings: list[str] = []
    plot = _figure(warnings, "recovery.png", plot_recovery, [r for r in merged if r["role"] != "reference"],
                   out / "recovery.png")
    protocol = protocol_block(ctx, merged, targets)
    protocol["active"] = rounds
    protocol_plot = _figure(warnings, "protocol.png", plot_protocol, protocol["optimizers"], out / "protocol.png",
                            ctx.spec.evaluation.reference, title=ctx.spec.name)
    renders = _renders(ctx, out, warnings)
    for w in warnings:
        ctx.log(f"warning: {w}", level=logging.WARNING)
    formats = set(ctx.spec.report.formats)
    names = list(targets["param_names"])
    flat = [{k: v for k, v in r.items() if k not in ("params", "history", "theta", "spread")}
            | {f"param_{n}": r["params"][n] for n in _in_space_order(r["params"], names)} for r in merged]
    files = []
    if "md" in formats:
        (out / "report.md").write_text(markdown(ctx.spec.name, merged, targets,
                                                plot.name if plot else None, renders,
                                                protocol, protocol_plot.name if protocol_plot else None,
                                                warnings=warnings, drawn=_drawn_note(ctx, targets, renders)))
        files.append("report.md")
    if "csv" in formats:
        pd.DataFrame(flat).to_csv(out / "report.csv", index=False)
        files.append("report.csv")
    summ = summary_table(merged, "target")
    if "json" in formats:
        write_json(out / "report.json", {"protocol": protocol["settings"], "optimizers": protocol["optimizers"],
                                         "active_learning": rounds,
                                         "parameters": protocol["parameters"],
                                         "uncertainty": protocol["uncertainty"], "summary": summ,
                                         "objectives": summary_table(merged, "objective"),
                                         "rows": flat, "targets": targets, "warnings": warnings},
                   indent=None, sort_keys=False)  # compact: 100 targets ~1.8 MB indented, ~1.2 MB compact;
        files.append("report.json")                # unsorted: parameters in the space's order
    ctx.log(f"wrote {', '.join(files)} to {out}")
    return {"files": files, "plot": plot.name if plot else None, "renders": [p for _, p, _ in renders],
            "warnings": warnings,
            "protocol_plot": protocol_plot.name if protocol_plot else None, "summary": summ,
            "optimizers": {k: {kk: v[kk] for kk in ("n_validated", "r_actual_mean", "r_actual_ci95",
                                                     f"vs_{ctx.spec.evaluation.reference}")}
                           for k, v in protocol["optimizers"].items()}}


def _in_space_order(params: dict[str, Any], names: list[str]) -> list[str]:
    """The keys of ``params`` in the parameter space's order (``names``), any others after them."""
    return [n for n in names if n in params] + [n for n in params if n not in names]


def _drawn_note(ctx: StageContext, targets: dict[str, Any], renders: list[tuple[int, str, str]]) -> str | None:
    """Which targets the report draws, when not all of them (None when all are, or drawing is off)."""
    from invphys.pipeline.stage_files import RENDER_TARGETS

    kept = RENDER_TARGETS
    if not ctx.spec.report.render:
        return None
    n = len(targets["rows"])
    drawn = sorted({k for k, _, _ in renders})
    if len(drawn) == n:
        return None
    which = ", ".join(str(k) for k in drawn) if drawn else "none"
    kept_text = f"the validate stage keeps the runs of its first {kept} targets only, and " if kept else ""
    return (f"Drawings (target vs recovered): {len(drawn)} of {n} targets ({which}); {kept_text}a target "
            f"without a validated answer (or whose drawing failed, see Warnings) is not drawn.")


def _with_device(ctx: StageContext, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Invert rows get the device their surrogate ran on (the cost's ``device``)."""
    try:
        device = str(getattr(ctx.surrogate(), "device", "cpu"))
    except Exception:
        device = None
    return [{**r, "device": r.get("device", device)} for r in rows]


def _evaluation_rows(ctx: StageContext, targets: dict[str, Any]) -> list[dict[str, Any]]:
    """The validate stage's evaluation rows; without a validate stage, the baselines answered here."""
    from invphys.pipeline.stage_files import baselines, load_evaluation_rows

    if ctx.finished("validate"):
        return load_evaluation_rows(ctx)
    if not ctx.spec.evaluation.baselines or ctx.spec.surrogate is None:
        return []
    return baselines(ctx, targets)[0]


def protocol_block(ctx: StageContext, merged: list[dict[str, Any]], targets: dict[str, Any]) -> dict[str, Any]:
    """The evaluation protocol's statistics, recovered parameters and uncertainty check."""
    from invphys.core.target_selection import target_set_labels
    from invphys.evaluation.method_summary import protocol_summary
    from invphys.evaluation.parameters import parameter_report
    from invphys.evaluation.uncertainty import uncertainty_check

    ev = ctx.spec.evaluation
    sets = target_set_labels(len(targets["rows"]), targets.get("selection", "farthest_point"))
    summary = protocol_summary(merged, sets, ev.reference, ev.bootstrap, ev.confidence, ctx.seed)
    units = None
    try:
        space = ctx.simulator().parameter_space()
        units = [space[n].unit for n in targets["param_names"]]
    except Exception:  # a simulator that cannot be built here: no units
        pass
    params = parameter_report(merged, targets, units, ev.spread_threshold, set_labels=sets)
    try:
        data = ctx.dataset()
        _, test_idx = ctx.split()
        unc = uncertainty_check(ctx.surrogate(), data.theta[test_idx], data.y[test_idx],
                                np.asarray(targets["scales"]), list(data.feature_names),
                                [r for r in merged if r["validated"]])
    except Exception as exc:  # no dataset or surrogate here: say so instead of failing the report
        unc = {"available": False, "note": f"{type(exc).__name__}: {exc}"}
    settings = {"targets": len(targets["rows"]), "validated": int(ctx.spec.targets.validate_n),
                "selection": targets.get("selection"), "sets": {s: sets.count(s) for s in dict.fromkeys(sets)},
                "reference": ev.reference, "bootstrap": ev.bootstrap, "confidence": ev.confidence,
                "failed_run_scores": 0.0}
    return {"settings": settings, "optimizers": summary, "parameters": params, "uncertainty": unc}


def _count(v: Any) -> str:
    """A per-target count (a mean): an integer when it is one."""
    if v is None:
        return "-"
    return str(round(v)) if abs(v - round(v)) < 1e-9 else f"{v:.1f}"


def _ci(v: Any) -> str:
    return "-" if not v else f"[{v[0]:.3f}, {v[1]:.3f}]"


def protocol_markdown(protocol: dict[str, Any], plot: str | None) -> list[str]:
    """The protocol section of report.md."""
    from invphys.evaluation.parameters import parameter_markdown

    st = protocol["settings"]
    ref = st["reference"]
    key = f"vs_{ref}"
    lines = ["## Protocol: R_actual with intervals, against the baselines", "",
             f"{st['targets']} held-out targets ({', '.join(f'{n} {s}' for s, n in st['sets'].items())}); "
             f"`targets.validate` = {st['validated']} (the n column counts the targets actually validated). Intervals: {st['bootstrap']} bootstrap resamples "
             f"over targets, {100 * st['confidence']:.0f} %. A failed validation run scores 0. A method beats "
             f"`{ref}` only when the paired interval's lower end is above 0. Cost per target: surrogate "
             f"evaluations, simulator runs, wall time, and the simulator's own time per target (GPU s, from the runs' "
             f"stats: a resumed run that replays memoised runs still counts them).", ""]
    table = []
    for lab, s in sorted(protocol["optimizers"].items(), key=lambda x: -(x[1]["r_actual_mean"] or -1)):
        d = s.get(key) or {}
        table.append([lab, s["role"], s["n_validated"], s["r_actual_mean"], _ci(s["r_actual_ci95"]),
                      s["r_surrogate_mean"], s["gap_mean"], d.get("mean_diff"), _ci(d.get("ci95")),
                      "yes" if d.get("beats") else ("-" if d.get("mean_diff") is None else "no"),
                      _count(s["evaluations"]), _count(s["simulator_runs"]),
                      s["wall_time_s"], s.get("simulator_time_s"), s["device"] or "-"])
    lines += _md_table(["method", "role", "n", "R_actual", "95 % CI", "R_surr", "Delta", f"diff vs {ref}",
                        "95 % CI", "beats", "evals/target", "sim runs/target", "time/target (s)", "GPU s/target",
                        "device"], table)
    by_set = {lab: s["by_set"] for lab, s in protocol["optimizers"].items()
              if s.get("by_set") and s["n_validated"]}
    for name in sorted({n for v in by_set.values() for n in v}):
        lines += ["", f"**{name} targets**", ""]
        lines += _md_table(["method", "n", "R_actual", "95 % CI", f"diff vs {ref}", "95 % CI"],
                           [[lab, v[name]["n_validated"], v[name]["r_actual_mean"], _ci(v[name]["r_actual_ci95"]),
                             (v[name].get(key) or {}).get("mean_diff"), _ci((v[name].get(key) or {}).get("ci95"))]
                            for lab, v in by_set.items()])
    if plot:
        lines += ["", f"![protocol]({plot})"]
    unc = protocol["uncertainty"]
    lines += ["", "### Does the surrogate know where it is wrong?", ""]
    if unc.get("available"):
        lines.append(f"Spearman rank correlation between the ensemble's normalised std and the surrogate's real "
                     f"normalised error on {unc['n_rows']} held-out rows: **{_fmt(unc['spearman_rows'])}**"
                     + (f"; between the std at validated answers and their |gap| ({unc['n_answers']} answers): "
                        f"**{_fmt(unc['spearman_answers'])}**" if "spearman_answers" in unc else "") + ".")
    else:
        lines.append(f"Not available: {unc.get('note')}.")
    if protocol.get("active"):
        lines += ["", "### Active learning rounds", "",
                  "Each round proposes one answer per target on the current surrogate, simulates them in one "
                  "batch, adds them to the training rows and retrains the surrogate.", ""]
        lines += _md_table(["round", "training rows", "surrogate R^2 (test)", "R_actual of proposals", "95 % CI",
                            "best so far", "95 % CI", "simulator runs", "simulator (s)", "device"],
                           [[a["round"], a["train_rows"], a["surrogate_r2_test"], a["r_actual_mean"],
                             _ci(a["r_actual_ci95"]), a["best_so_far_mean"], _ci(a["best_so_far_ci95"]),
                             a["simulator_runs"], a["simulator_s"], a["device"] or "-"] for a in protocol["active"]])
    lines += ["", *parameter_markdown(protocol["parameters"], max_targets=20)]
    return lines

