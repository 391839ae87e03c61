"""Recovered parameters per target and method, their error against the truth, and identifiability.

Errors are in normalised parameter space ([0, 1]^d, the space the data was sampled in) against the
held-out row's true parameters. A parameter is flagged as *not pinned down* for a target when its
spread, in units of the prior's std (U(0, 1): 0.289), exceeds ``threshold``: the spread of the npe
baseline's posterior when there is one, else the spread of the answers of the methods that score
within ``top_margin`` of the best on that target.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from invphys.evaluation.method_summary import actual_score

PRIOR_STD = float(np.sqrt(1.0 / 12.0))


def _score(row: dict[str, Any]) -> float:
    v = actual_score(row)
    return v if np.isfinite(v) else float(row.get("r_surrogate") or np.nan)


def parameter_report(rows: list[dict[str, Any]], targets: dict[str, Any], units: list[str] | None = None,
                     threshold: float = 0.5, top_margin: float = 0.05,
                     set_labels: list[str] | None = None) -> dict[str, Any]:
    """The ``parameters`` block of ``report.json`` (see the module docstring).

    Parameter values are lists in the order of ``names`` (physical units, ``units``); ``error`` lists
    are |theta - theta_true| in normalised space, in the same order.
    """
    names = list(targets["param_names"])
    d = len(names)
    units = list(units) if units else [""] * d
    has_truth = targets.get("theta") is not None  # user targets (targets.values / file) have none
    truth_theta = np.asarray(targets["theta"], dtype=np.float64) if has_truth else None
    truth_params = np.asarray(targets["params"], dtype=np.float64) if has_truth else None
    trows = [r for r in rows if r["problem"] == "target" and r.get("target_index") is not None
             and r.get("role") != "reference"]
    labels = list(dict.fromkeys(r["optimizer"] for r in trows))
    errors: dict[str, list[np.ndarray]] = {lab: [] for lab in labels}
    per_target = []
    flagged_count = np.zeros(d)
    spreads_all = []
    for k in sorted({int(r["target_index"]) for r in trows}):
        mine = [r for r in trows if int(r["target_index"]) == k]
        methods: dict[str, Any] = {}
        for r in mine:
            th = np.asarray(r["theta"], dtype=np.float64)
            err = None if truth_theta is None else np.abs(th - truth_theta[k])
            if err is not None:
                errors[r["optimizer"]].append(err)
            values = r.get("params") or {}
            methods[r["optimizer"]] = {
                "params": [values.get(n) for n in names], "error": None if err is None else err.tolist(),
                "rms_error": None if err is None else float(np.sqrt(np.mean(err ** 2))),
                "r_actual": None if not np.isfinite(actual_score(r)) else actual_score(r)}
        spread, source = None, None
        post = [r for r in mine if r.get("type") == "npe" and r.get("spread") is not None]
        if post:
            spread, source = np.asarray(post[0]["spread"], dtype=np.float64), "npe"
        else:
            scores = np.array([_score(r) for r in mine])
            if np.isfinite(scores).sum() >= 2:
                best = np.nanmax(scores)
                top = [r for r, s in zip(mine, scores, strict=True) if np.isfinite(s) and s >= best - top_margin]
                if len(top) >= 2:
                    spread = np.std([r["theta"] for r in top], axis=0) / PRIOR_STD
                    source = f"top {len(top)} methods"
        flags = [] if spread is None else [n for n, s in zip(names, spread, strict=True) if s > threshold]
        if spread is not None:
            flagged_count += spread > threshold
            spreads_all.append(spread)
        per_target.append({
            "target_index": k, "dataset_row": targets["rows"][k] if k < len(targets["rows"]) else None,
            "set": set_labels[k] if set_labels and k < len(set_labels) else targets.get("selection"),
            "truth": None if truth_params is None else truth_params[k].tolist(),
            "methods": methods, "spread": None if spread is None else spread.tolist(), "spread_source": source,
            "not_pinned_down": flags})
    n_spread = len(spreads_all)
    med = np.median(np.array(spreads_all), axis=0) if n_spread else np.full(d, np.nan)
    frac = flagged_count / n_spread if n_spread else np.full(d, np.nan)
    error_summary = {}
    for lab, errs in errors.items():
        if errs:
            e = np.array(errs)
            error_summary[lab] = {"n": len(e), "mean_abs": e.mean(axis=0).tolist(),
                                  "rms": float(np.sqrt(np.mean(e ** 2))), "mean_abs_all": float(e.mean())}
    return {
        "names": names, "units": units, "threshold": threshold,
        "error": error_summary,
        "identifiability": {
            "targets_with_spread": n_spread,
            "per_parameter": [{"name": n, "unit": u, "median_spread": None if not np.isfinite(m) else float(m),
                               "flagged_fraction": None if not np.isfinite(f) else float(f)}
                              for n, u, m, f in zip(names, units, med, frac, strict=True)],
            "not_pinned_down": [n for n, f in zip(names, frac, strict=True) if np.isfinite(f) and f >= 0.5]},
        "targets": per_target}


def _md_table(header: list[str], rows: list[list[Any]]) -> list[str]:
    def cell(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3f}" if np.isfinite(v) else "n/a"
        return str(v)

    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|",
            *["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]]


def _g(v: Any) -> str:
    return "-" if v is None else f"{float(v):.4g}"


def parameter_markdown(block: dict[str, Any], max_targets: int | None = None) -> list[str]:
    """Markdown lines: error per method and parameter, identifiability, and per-target tables."""
    names, units = block["names"], block["units"]
    heads = [f"{n} [{u}]" if u else n for n, u in zip(names, units, strict=True)]
    lines = ["## Recovered parameters", "",
             "Mean |theta - theta_true| per parameter in normalised space [0, 1] (held-out rows; "
             "0.33 is a uniform guess's expected error).", ""]
    lines += _md_table(["method", "n", *names, "RMS"],
                       [[lab, e["n"], *e["mean_abs"], e["rms"]] for lab, e in block["error"].items()])
    ident = block["identifiability"]
    lines += ["", f"Spread of each parameter in units of the prior's std (flag above {block['threshold']}: "
              f"the features do not pin it down), over {ident['targets_with_spread']} targets.", ""]
    lines += _md_table(["parameter", "median spread", "flagged on"],
                       [[p["name"], p["median_spread"],
                         "-" if p["flagged_fraction"] is None else f"{100 * p['flagged_fraction']:.0f} %"]
                        for p in ident["per_parameter"]])
    if ident["not_pinned_down"]:
        lines += ["", f"**Not pinned down by the data** (flagged on >= half the targets): "
                  f"{', '.join(ident['not_pinned_down'])}."]
    lines.append("")
    for t in block["targets"][:max_targets]:
        lines += [f"### Target {t['target_index']} ({t['set']}, dataset row {t['dataset_row']})", ""]
        rows = [] if t["truth"] is None else [["truth", *[_g(v) for v in t["truth"]], "-", "-"]]
        rows += [[lab, *[_g(v) for v in m["params"]], m["rms_error"], m["r_actual"]]
                 for lab, m in t["methods"].items()]
        lines += _md_table(["method", *heads, "RMS error", "R_actual"], rows)
        if t["not_pinned_down"]:
            lines += ["", f"Not pinned down here ({t['spread_source']}): {', '.join(t['not_pinned_down'])}"]
        lines.append("")
    return lines
