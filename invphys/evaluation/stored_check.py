"""``invphys diagnose BUNDLE --check-stored``: the bundle's STORED recalibration on held-out rows its
diagnosis did not use.

``invphys diagnose --write`` measures a bundle on at most ``--rows`` held-out rows (the first by key) and
fits the stored recalibration on all of them, so its numbers are out of fold but the stored block itself
is never checked on rows it did not see. This check takes the held-out rows (:mod:`~invphys.evaluation.heldout`)
minus the rows the stored diagnosis used, draws the posterior the stored calibration names, applies the
stored block as answers do (:func:`~invphys.evaluation.calibration.recalibrated_samples`, no refit) and
measures coverage per parameter (with bootstrap intervals and widths), TARP (one and
:data:`~invphys.evaluation.calibration.TARP_REFS` references per row), SBC and the clipped share, before
and after the stored correction.

The rows the diagnosis used are read from ``diagnostics/rows_used.json`` (their keys, written by
``invphys diagnose`` since this check exists); for diagnostics written before it, they are rebuilt from
``report.json``: its first ``rows_used`` held-out rows by key of the stores it names, accepted only when
those stores give the same held-out rows per store as the report recorded.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.evaluation import calibration as cal

ROWS_USED_FILE = "rows_used.json"
CHECK_FILE = "check_unused_rows.json"
#: the bar a level is judged against (|coverage - level|)
TOLERANCE = 0.03
_LEVELS = ("0.5", "0.8", "0.9", "0.95")


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        data = None
    if not isinstance(data, dict):
        raise InvphysError(f"{path} is not a readable JSON object; run invphys diagnose {path.parent.parent} "
                           f"--write again")
    return data


def stored_diagnostics(root: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """(calibration.json, report.json) of a bundle's stored diagnostics, which must hold a recalibration block."""
    d = Path(root) / "diagnostics"
    if not (d / "calibration.json").is_file() or not (d / "report.json").is_file():
        raise InvphysError(f"bundle {root} holds no stored diagnostics to check: run invphys diagnose {root} "
                           f"--write first")
    calib, report = _read_json(d / "calibration.json"), _read_json(d / "report.json")
    if calib.get("bundle_id") != report.get("bundle_id"):
        raise InvphysError(f"bundle {root}: its diagnostics' calibration.json and report.json disagree")
    if not isinstance((calib.get("posterior") or {}).get("recalibration"), dict):
        raise InvphysError(f"bundle {root}: its stored diagnostics hold no posterior recalibration to check")
    return calib, report


def recalibration_digest(calib: dict[str, Any]) -> str:
    """A short hash of the stored posterior block (method, parameters, recalibration): what was checked."""
    post = calib["posterior"]
    text = json.dumps({k: post.get(k) for k in ("method", "parameters", "recalibration")}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def used_keys(bundle: Any, report: dict[str, Any]) -> tuple[set[str], str]:
    """(keys of the rows the stored diagnosis used, how they were found)."""
    from invphys.evaluation.heldout import heldout_rows

    path = Path(bundle.root) / "diagnostics" / ROWS_USED_FILE
    if path.is_file():
        keys = _read_json(path).get("keys")
        if not isinstance(keys, list):
            raise InvphysError(f"{path} holds no list of keys")
        return {str(k) for k in keys}, f"the {len(keys)} keys in diagnostics/{ROWS_USED_FILE}"
    h = report.get("heldout") or {}
    stores, n = h.get("stores"), h.get("rows_used")
    if not isinstance(stores, dict) or not stores or not isinstance(n, int):
        raise InvphysError(f"bundle {bundle.root}: its stored report names neither the rows it used nor its "
                           f"stores; run invphys diagnose {bundle.root} --write again")
    held = heldout_rows(bundle, list(stores))
    now = {s: v.get("held_out") for s, v in held.info["stores"].items()}
    if now != {s: (v or {}).get("held_out") for s, v in stores.items()} or len(held) != h.get("rows"):
        raise InvphysError(f"bundle {bundle.root}: the stores its stored report names no longer give the held-out "
                           f"rows it recorded ({now}); the rows it used cannot be told apart")
    return set(held.keys[:n].astype(str).tolist()), (f"rebuilt from report.json: the first {n} by key of its "
                                                     f"{h.get('rows')} held-out rows (same stores, same counts)")


def _unused(bundle: Any, report: dict[str, Any], stores: Any, rows: int | None
            ) -> tuple[Any, dict[str, Any], set[str]]:
    """(held-out rows the stored diagnosis did not use, at most ``rows`` first by key; what was left out;
    the used keys)."""
    from invphys.evaluation.heldout import heldout_rows

    used, how = used_keys(bundle, report)
    given = stores or list((report.get("heldout") or {}).get("stores") or {})
    held = heldout_rows(bundle, given or None)
    fresh = np.array([str(k) not in used for k in held.keys], dtype=bool)
    held = held.take(np.flatnonzero(fresh))
    if rows is not None:
        held = held.take(np.arange(min(int(rows), len(held))))
    if len(held) < 20:
        raise InvphysError(f"bundle {bundle.root}: only {len(held)} held-out rows the stored diagnosis did not "
                           f"use; the check needs >= 20 (point --data at more stores of its simulator)")
    return held, {"used_by_stored_diagnosis": len(used), "found_by": how, "left_out_here": int((~fresh).sum())}, used


def _block(samples: np.ndarray, theta: np.ndarray, seed: int) -> dict[str, Any]:
    return {"coverage": cal.central_coverage(samples, theta, seed=seed), "tarp": cal.tarp(samples, theta, seed=seed),
            "sbc": cal.sbc(samples, theta)}


def _verdict(after: dict[str, Any], names: list[str], identified: list[bool]) -> dict[str, Any]:
    """Per identified parameter and jointly (TARP, all references): worst |coverage - level|, and whether
    every level is within :data:`TOLERANCE`."""
    per = {n: max(abs(after["coverage"][k]["coverage"][j] - float(k)) for k in _LEVELS)
           for j, n in enumerate(names) if identified[j]}
    joint = max(abs(after["tarp"]["levels_refs"][k]["rate"] - float(k)) for k in _LEVELS)
    return {"tolerance": TOLERANCE, "worst_error_identified": per, "worst_error_tarp_refs": joint,
            "within": bool(all(v <= TOLERANCE for v in per.values()) and joint <= TOLERANCE)}


def check_stored(inverter: Any, stores: Any = None, rows: int | None = None, draws: int = 1000,
                 seed: int = 0) -> tuple[dict[str, Any], list[str] | None]:
    """Measure the bundle's stored recalibration on held-out rows its stored diagnosis did not use:
    (the check, the used keys when they were rebuilt rather than read from ``rows_used.json``)."""
    from invphys.evaluation.diagnose import _draws_in_chunks, _plain

    bundle = inverter.bundle
    calib, report = stored_diagnostics(bundle.root)
    if calib.get("bundle_id") != bundle.manifest.get("bundle_id"):
        raise InvphysError(f"bundle {bundle.root}: its stored diagnostics were written for another bundle id")
    held, excluded, used = _unused(bundle, report, stores, rows)
    post = calib["posterior"]
    names = list(bundle.space.names)
    samples, outside, clipped = _draws_in_chunks(inverter, held.y, draws, seed, post["method"])
    fixed = cal.recalibrated_samples(samples, calib)
    width90 = (calib.get("identified") or {}).get("width90") or [0.0] * len(names)
    identified = [float(w) < float((calib.get("identified") or {}).get("max_width90", 0.5)) for w in width90]
    after = _block(fixed, held.theta, seed)
    out = {"what": "the stored recalibration (no refit) on held-out rows the stored diagnosis did not use",
           "bundle_id": bundle.manifest.get("bundle_id"), "checked": recalibration_digest(calib),
           "stored_created_utc": calib.get("created_utc"), "recalibrated": report.get("recalibrated", []),
           "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "seed": int(seed),
           "parameters": names, "posterior_method": post["method"], "draws_per_row": int(draws),
           "rows": {"n": len(held), "keys_fingerprint": _fingerprint(held.keys), **excluded,
                    "stores": sorted({str(s) for s in held.source}), "picked": "held-out rows minus the stored "
                    "diagnosis's rows, the first by key when --rows is given"},
           "not_identified": [n for n, k in zip(names, identified, strict=True) if not k],
           "clipped_share": float(clipped.sum() / (draws * len(clipped))),
           "mean_outside_fraction": float(outside.mean()),
           "before": _block(samples, held.theta, seed), "after": after,
           "verdict": _verdict(after, names, identified)}
    rebuilt = None if (Path(bundle.root) / "diagnostics" / ROWS_USED_FILE).is_file() else sorted(used)
    return dict(_plain(out)), rebuilt


def _fingerprint(keys: np.ndarray) -> str:
    from invphys.core.dataset import keys_fingerprint

    return str(keys_fingerprint([str(k) for k in keys]))


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _ci(b: dict[str, Any], j: int | None = None) -> str:
    rate, ci = (b["rate"], b["ci95"]) if j is None else (b["coverage"][j], b["ci95"][j])
    return f"{_pct(rate)} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def check_markdown(check: dict[str, Any]) -> str:
    """The check as Markdown: per parameter and jointly, coverage after the stored correction with 95 %
    bootstrap intervals, the 90 % width and SBC p."""
    r, a, b = check["rows"], check["after"], check["before"]
    lines = [f"Check on unused rows: the stored recalibration (no refit; recalibrated: "
             f"{', '.join(check['recalibrated']) or 'none'}) on {r['n']} held-out rows the stored diagnosis did not "
             f"use (its {r['used_by_stored_diagnosis']} rows left out; they are {r['found_by']}); "
             f"{check['draws_per_row']} draws per row of `{check['posterior_method']}`. Coverage after the stored "
             f"correction with 95 % bootstrap intervals (nominal 50/80/90/95 %):", "",
             "| parameter | 50 % | 80 % | 90 % | 95 % | 90 % width | SBC p before -> after |", "|---|---|---|---|---|---|---|"]
    for j, n in enumerate(check["parameters"]):
        mark = " (not identified)" if n in check["not_identified"] else ""
        lines.append(f"| {n}{mark} | " + " | ".join(_ci(a["coverage"][k], j) for k in _LEVELS)
                     + f" | {a['coverage']['0.9']['width'][j]:.2f} | {b['sbc']['ks_pvalue'][j]:.2g} -> "
                       f"{a['sbc']['ks_pvalue'][j]:.2g} |")
    lines.append("| joint (TARP, 1 reference) | " + " | ".join(_ci(a["tarp"]["levels"][k]) for k in _LEVELS) + " | | |")
    lines.append(f"| joint (TARP, {a['tarp']['n_refs']} references) | "
                 + " | ".join(_ci(a["tarp"]["levels_refs"][k]) for k in _LEVELS) + " | | |")
    v = check["verdict"]
    worst = ", ".join(f"{n} {e:.3f}" for n, e in v["worst_error_identified"].items())
    lines += ["", f"Worst |coverage - level| over 50/80/90/95 %: {worst or 'no identified parameter'}; joint (TARP, "
                  f"{a['tarp']['n_refs']} references) {v['worst_error_tarp_refs']:.3f}: "
                  f"{'all within' if v['within'] else 'not all within'} ±{v['tolerance']:g}. Draws clipped into the "
                  f"box: {_pct(check['clipped_share'])}. Checked block {check['checked']}."]
    return "\n".join(lines) + "\n"


def write_check(check: dict[str, Any], out: Path) -> list[Path]:
    """``check_unused_rows.json`` and ``check_unused_rows.md`` in ``out`` (created)."""
    from invphys.core.atomic import atomic_write_bytes

    out.mkdir(parents=True, exist_ok=True)
    js, md = out / CHECK_FILE, out / "check_unused_rows.md"
    atomic_write_bytes(js, (json.dumps(check, indent=1, allow_nan=False) + "\n").encode())
    atomic_write_bytes(md, check_markdown(check).encode())
    return [js, md]
