"""Writing a :class:`~invphys.evaluation.diagnose.Diagnosis`: JSON, a Markdown summary and two figures.

Files: ``report.json`` (everything measured), ``calibration.json`` (the numbers answers use),
``summary.md`` (the table a bundle's README shows), ``rank_histograms.png``, ``coverage.png``.
:func:`write_into_bundle` puts them in a bundle's ``diagnostics/`` folder, adds the summary to its
README and re-hashes the manifest's file list (:func:`invphys.inverter.manifest.write_manifest`);
:func:`write_failure_into_bundle` adds a fitted failure warning to the diagnostics a bundle holds.
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.atomic import atomic_write_bytes

DIAGNOSTICS_DIR = "diagnostics"
README_HEADING = "## Diagnostics (invphys diagnose)"


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def summary_markdown(report: dict[str, Any]) -> str:
    """The measured summary as Markdown (check half, before and after recalibration)."""
    h = report["heldout"]
    lines = [f"Measured on {h['rows_used']} held-out rows the bundle never trained on (picked by key; "
             f"{h['fit_rows']} fit the corrections, {h['check_rows']} check them)."]
    if report.get("check_before"):
        lines += _posterior_lines(report)
    else:
        lines += ["", f"No posterior checked ({report.get('note', 'the bundle has no method with a posterior')})."]
    lines += ["", _ood_line(report["ood"])]
    if report.get("failure"):
        lines.append(failure_line(report["failure"]))
    s = report["surrogate_error_bars"]
    if s.get("available"):
        lines.append(f"Surrogate error bars (±1.645 sigma): hold {_pct(s['check_before']['overall'])} of held-out "
                     f"errors with the raw ensemble spread, {_pct(s['check_after']['overall'])} scaled (nominal 90 %).")
    if report.get("check_unused_rows"):  # added by invphys diagnose --check-stored --write
        from invphys.evaluation.stored_check import check_markdown

        lines += ["", check_markdown(report["check_unused_rows"]).rstrip("\n")]
    return "\n".join(lines) + "\n"


def _posterior_lines(report: dict[str, Any]) -> list[str]:
    names = report["parameters"]
    lines = [f"Posterior: {report['draws_per_row']} draws per row from `{report['posterior_method']}`.", "",
             "Central-interval coverage on the check rows, before -> after the recalibration fitted on the fit rows "
             "(out of fold; nominal 50/80/90/95 %):",
             "", "| parameter | 50 % | 80 % | 90 % | 95 % | 90 % width | SBC p before -> after |",
             "|---|---|---|---|---|---|---|"]
    b, a = report["check_before"], report["check_after"]
    for j, n in enumerate(names):
        cells = [f"{_pct(b['coverage'][k]['coverage'][j])} -> {_pct(a['coverage'][k]['coverage'][j])}"
                 for k in ("0.5", "0.8", "0.9", "0.95")]
        mark = "" if n not in report["identified"]["not_identified"] else " (not identified)"
        lines.append(f"| {n}{mark} | {' | '.join(cells)} | {b['coverage']['0.9']['width'][j]:.2f} | "
                     f"{b['sbc']['ks_pvalue'][j]:.2g} -> {a['sbc']['ks_pvalue'][j]:.2g} |")
    tb, ta = b["tarp"]["levels"], a["tarp"]["levels"]
    lines.append("| joint (TARP) | " + " | ".join(f"{_pct(tb[k]['rate'])} -> {_pct(ta[k]['rate'])}"
                                                  for k in ("0.5", "0.8", "0.9", "0.95")) + " | | |")
    rb, ra = b["tarp"].get("levels_refs"), a["tarp"].get("levels_refs")
    if rb and ra:  # the same expected coverage over several reference points per row: less noise
        lines.append(f"| joint (TARP, {a['tarp'].get('n_refs')} references per row) | "
                     + " | ".join(f"{_pct(rb[k]['rate'])} -> {_pct(ra[k]['rate'])} "
                                  f"[{_pct(ra[k]['ci95'][0])}, {_pct(ra[k]['ci95'][1])}]"
                                  for k in ("0.5", "0.8", "0.9", "0.95")) + " | | |")
    lines += _fold_lines(report)
    lines += ["", f"Recalibrated: {', '.join(report['recalibrated']) or 'none'}. "
              f"Not identified (90 % interval wider than {report['identified']['max_width90']:.0%} of the range): "
              f"{', '.join(report['identified']['not_identified']) or 'none'}. "
              f"Raw draws outside the box: {_pct(report['outside_box']['mean_outside_fraction'])} (rejected); "
              f"draws clipped into it: {_pct(report['outside_box'].get('clipped_share', 0.0))} "
              f"({report['outside_box'].get('rows_with_clipping', 0)} rows)."]
    sw = report.get("swapped")
    if sw:
        w = sw["after"]
        lines.append("The other direction (fitted on the check rows, checked on the fit rows), 50/80/90/95 %: worst "
                     "parameter off by " + ", ".join(f"{max(abs(c - float(k)) for c in w['coverage'][k]['coverage']):.3f}"
                                                      for k in ("0.5", "0.8", "0.9", "0.95"))
                     + "; joint (TARP) " + ", ".join(_pct(w["tarp"]["levels"][k]["rate"])
                                                     for k in ("0.5", "0.8", "0.9", "0.95")) + ".")
    for v in report["after_recalibration_not_uniform"]:
        lines.append(f"SBC ranks of {v['parameter']} stay non-uniform after recalibration (p {v['ks_pvalue']:.2g}, "
                     f"bias {v['bias']:+.3f}): {v['reading']}.")
    return lines


def _fold_lines(report: dict[str, Any]) -> list[str]:
    """The two-fold acceptance rule's evidence per parameter (reports written before it have none)."""
    r = report.get("recalibration")
    if not r:
        return []
    lines = ["", f"Which parameters are recalibrated: {r['rule']}; the stored recalibration is then fitted on "
                 f"{r['fitted_on']}. Out-of-fold coverage error, before -> after:",
             "", "| parameter | recalibrated | fitted on fit rows, checked on check rows | fitted on check rows, "
                 "checked on fit rows |", "|---|---|---|---|"]
    for n, v in r["parameters"].items():
        lines.append(f"| {n} | {'yes' if v['recalibrated'] else 'no'} | {v['a_to_b']['before']:.3f} -> "
                     f"{v['a_to_b']['after']:.3f} | {v['b_to_a']['before']:.3f} -> {v['b_to_a']['after']:.3f} |")
    return lines


def _ood_line(o: dict[str, Any]) -> str:
    fires = f"warning above {o['threshold']:.3g}: fires on {_pct(o['check']['fire_rate'])} of check rows"
    if not o["candidates"]:
        return f"Out-of-distribution score: `{o['chosen']}` (not measured against failures: {o.get('note')}); {fires}."
    auc, failing = o["candidates"][o["chosen"]], o["failure"].get("failing_check") or {}
    return (f"Out-of-distribution score: `{o['chosen']}`, AUROC on the check rows "
            f"{_auc(auc['r_surr']['check'], failing.get('r_surr'))} "
            f"for answers that do not reproduce their target (R_surr < {o['failure']['r_surr_below']:g}"
            f"{_stored_note(o['failure'])}), "
            f"{_auc(auc['parameter_error']['check'], failing.get('parameter_error'))} for answers whose error over "
            f"the identified parameters "
            f"exceeds {o['failure']['parameter_error_above']:g}; {fires} and on "
            f"{_pct(o['check']['recall_r_surr']) if o['check'].get('recall_r_surr') is not None else 'n/a (none)'} "
            f"of those whose answer does not reproduce the target.")


#: fewer failing check rows than this and an AUROC says little (one row moves it by 1 / n)
FEW_FAILING = 10


def _auc(value: float | None, failing: int | None) -> str:
    """An AUROC with the number of failing rows it rests on (reports without the count: the number alone)."""
    if failing is None:
        return _f2(value)
    if failing < FEW_FAILING:
        return f"{_f2(value)} (on only {failing} failing rows: too few to rank the score)"
    return f"{_f2(value)} ({failing} failing rows)"


def _stored_note(failure: dict[str, Any]) -> str:
    n = failure.get("stored_rows_by_real_r") or 0
    return f"; {n} answers that are stored rows by their real R" if n else ""


def failure_line(f: dict[str, Any]) -> str:
    """One sentence on the answer-level failure warning (``failure`` of a report or calibration)."""
    c, rows = f["calibration"], f.get("rows") or {}
    left = (f"; {rows['training_rows']} rows that are training rows of the bundle left out"
            if rows.get("training_rows") and not rows.get("training_rows_used") else "")
    return (f"Failure warning (answer-level, scores {', '.join(f['scores'])}): fitted on {c['n']} validated held-out "
            f"answers of `{f.get('method')}` ({c['failing']} with R_actual < {f['fail_below']:g}{left}); at failure "
            f"score >= {f['threshold']:.3g} it catches {_pct(c['recall'])} of the failing answers and fires on "
            f"{_pct(c['alarm_rate'])} of the others (AUROC {_f2(c['auroc'])}, measured on the rows that fitted it)."
            + (f" Kept {f['kept']}." if f.get("kept") else ""))


def _f2(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}"


def plot_ranks(ranks_before: np.ndarray, ranks_after: np.ndarray, n_draws: int, names: list[str], path: Path) -> Path:
    """One panel per parameter: SBC rank histograms before and after recalibration, with the uniform band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import binom

    d, bins = len(names), 20
    cols = 3
    fig, axes = plt.subplots((d + cols - 1) // cols, cols, figsize=(4 * cols, 2.6 * ((d + cols - 1) // cols)))
    n = len(ranks_before)
    lo, hi = binom.ppf([0.005, 0.995], n, 1 / bins)
    for j, ax in enumerate(np.atleast_1d(axes).ravel()):
        if j >= d:
            ax.axis("off")
            continue
        ax.axhspan(lo, hi, color="0.85")
        ax.hist(ranks_before[:, j], bins=bins, range=(0, n_draws + 1), histtype="step", color="C3", label="before")
        ax.hist(ranks_after[:, j], bins=bins, range=(0, n_draws + 1), histtype="step", color="C0", label="after")
        ax.set_title(names[j], fontsize=9)
        ax.set_yticks([])
    np.atleast_1d(axes).ravel()[0].legend(fontsize=7)
    fig.suptitle("SBC ranks on the check rows, before and after recalibration "
                 "(grey: 99 % band of a uniform histogram)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_coverage(report: dict[str, Any], path: Path) -> Path:
    """Empirical against nominal coverage per parameter and jointly (TARP), before and after recalibration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.4), sharey=True)
    levels = [float(k) for k in report["check_before"]["coverage"]]
    for ax, key, title in ((axes[0], "check_before", "before"), (axes[1], "check_after", "after recalibration")):
        block = report[key]
        for j, n in enumerate(report["parameters"]):
            ax.plot(levels, [block["coverage"][f"{lv:g}"]["coverage"][j] for lv in levels], "o-", lw=1, ms=3, label=n)
        curve = block["tarp"]["curve"]
        ax.plot(curve["alpha"], curve["ecp"], "k-", lw=2, label="joint (TARP)")
        ax.plot([0, 1], [0, 1], ":", color="0.5")
        ax.set_xlabel("nominal level")
        ax.set_title(title, fontsize=10)
    axes[0].set_ylabel("share of rows whose truth is inside")
    axes[1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def write_report(diagnosis: Any, out: Path) -> list[Path]:
    """Write every file into ``out`` (created); returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    r = diagnosis.report
    files = [_json(out / "report.json", r), _json(out / "calibration.json", diagnosis.calibration)]
    md = out / "summary.md"
    atomic_write_bytes(md, summary_markdown(r).encode())
    files.append(md)
    if getattr(diagnosis, "keys", None) is not None:  # the rows it used, by key (invphys diagnose --check-stored)
        files.append(_json(out / "rows_used.json", {"bundle_id": r.get("bundle_id"), "keys": list(diagnosis.keys)}))
    if "ranks_before" in diagnosis.figures:
        files.append(plot_ranks(diagnosis.figures["ranks_before"], diagnosis.figures["ranks_after"],
                                r["draws_per_row"], r["parameters"], out / "rank_histograms.png"))
    if r.get("check_before"):
        files.append(plot_coverage(r, out / "coverage.png"))
    return files


def _json(path: Path, data: Any) -> Path:
    atomic_write_bytes(path, (json.dumps(data, indent=1, allow_nan=False) + "\n").encode())
    return path


def write_into_bundle(diagnosis: Any, root: Path) -> Path:
    """Replace ``root/diagnostics`` with this diagnosis, put its summary in the README, re-hash the manifest.

    All of it happens in a copy of the bundle beside it, which is checked (every file against its new
    hash) and then swapped in, so a killed run leaves the old bundle or the new one, never a bundle whose
    README no longer matches its manifest.
    """
    def edit(tmp: Path) -> dict[str, Any]:
        shutil.rmtree(tmp / DIAGNOSTICS_DIR, ignore_errors=True)
        write_report(diagnosis, tmp / DIAGNOSTICS_DIR)
        return diagnosis.report  # type: ignore[no-any-return]

    return _swap_in(Path(root), edit)


def write_failure_into_bundle(model: dict[str, Any], root: Path) -> Path:
    """Store a fitted failure model (:func:`invphys.evaluation.failure_score.fit`) in the bundle's existing
    diagnostics (``calibration.json`` and ``report.json`` get its ``failure`` block, the summary and README
    its line), re-hashing the manifest as :func:`write_into_bundle` does; nothing else changes."""
    from invphys.core.errors import InvphysError

    root = Path(root)
    if not (root / DIAGNOSTICS_DIR / "calibration.json").is_file() or not (root / DIAGNOSTICS_DIR / "report.json").is_file():
        raise InvphysError(f"bundle {root} holds no diagnostics yet: run invphys diagnose {root} --write first")

    def edit(tmp: Path) -> dict[str, Any]:
        d = tmp / DIAGNOSTICS_DIR
        cal, report = (json.loads((d / n).read_text()) for n in ("calibration.json", "report.json"))
        if cal.get("bundle_id") != report.get("bundle_id"):
            raise InvphysError(f"bundle {root}: its diagnostics' calibration.json and report.json disagree")
        cal["failure"] = report["failure"] = model
        _json(d / "calibration.json", cal)
        _json(d / "report.json", report)
        atomic_write_bytes(d / "summary.md", summary_markdown(report).encode())
        return report  # type: ignore[no-any-return]

    return _swap_in(root, edit)


def write_check_into_bundle(check: dict[str, Any], root: Path, used: list[str] | None = None) -> Path:
    """Add a check on unused rows (:func:`invphys.evaluation.stored_check.check_stored`) to the bundle's
    diagnostics: ``check_unused_rows.json``, the ``check_unused_rows`` block of ``report.json``, the summary
    and README; ``used`` (the keys the stored diagnosis used, when it did not record them) goes to
    ``rows_used.json``. Refused when the stored recalibration is no longer the one checked."""
    from invphys.core.errors import InvphysError
    from invphys.evaluation import stored_check as sc

    root = Path(root)

    def edit(tmp: Path) -> dict[str, Any]:
        calib, report = sc.stored_diagnostics(tmp)
        if sc.recalibration_digest(calib) != check["checked"]:
            raise InvphysError(f"bundle {root}: its stored recalibration changed since it was checked; check again")
        d = tmp / DIAGNOSTICS_DIR
        report["check_unused_rows"] = check
        _json(d / "report.json", report)
        sc.write_check(check, d)
        if used is not None and not (d / sc.ROWS_USED_FILE).is_file():
            _json(d / sc.ROWS_USED_FILE, {"bundle_id": report.get("bundle_id"), "keys": sorted(used)})
        atomic_write_bytes(d / "summary.md", summary_markdown(report).encode())
        return report

    return _swap_in(root, edit)


def _swap_in(root: Path, edit: Any) -> Path:
    """Apply ``edit`` (returns the report) to a checked copy of the bundle, refresh the README's summary and
    the manifest, check it, swap it in."""
    from invphys.inverter.manifest import read_manifest, write_manifest

    tmp = root.with_name(f".{root.name}.diag{uuid.uuid4().hex[:6]}")
    old = root.with_name(f".{root.name}.old{uuid.uuid4().hex[:6]}")
    shutil.copytree(root, tmp, symlinks=True)
    try:
        manifest = read_manifest(tmp, verify=True)
        report = edit(tmp)
        readme = tmp / "README.md"
        text = readme.read_text() if readme.is_file() else ""
        text = text.split("\n" + README_HEADING)[0].rstrip("\n")
        atomic_write_bytes(readme, (text + "\n\n" + README_HEADING + "\n\n" + summary_markdown(report)).encode())
        manifest["diagnostics"] = {"path": DIAGNOSTICS_DIR, "created_utc": report["created_utc"],
                                   "rows": report["heldout"]["rows_used"]}
        write_manifest(tmp, manifest)
        read_manifest(tmp, verify=True)
        root.rename(old)
        tmp.rename(root)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)
    return root / DIAGNOSTICS_DIR
