"""Fit a bundle's answer-level failure warning on validated held-out answers; measure it on other sets.

    python benchmarks/fit_failure_warning.py --bundle inverters/orange_peel_paper \\
        --calibration runs/per_target_heldout.json:heldout --report runs/per_target_fresh.json \\
        --out benchmarks/results/failure_warning_paper.json

``--calibration FILE[:SET]``: validated answers (``bench_user_targets.py --validate --per-target-out``) of
rows the bundle never trained on; the model and its threshold are fitted on them alone. ``--report
FILE[:SET]``: sets it is measured on (never fitted on). Every score's AUROC, the model's, recall on failing
answers (R_actual < 0.8) and the alarm rate on the others are written per set, with the target-only
``knn`` warning's at its stored threshold beside them. Calibration rows whose true parameters are training
rows of the bundle are counted and left out (``--keep-training`` keeps them). ``--write`` stores the model
in the bundle's diagnostics (``invphys diagnose BUNDLE --write --failures FILE[:SET]`` fits the same model on
the same rows while it re-measures everything else).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np


def _sets(spec: str) -> tuple[str, tuple[str, ...] | None]:
    path, name = (spec, "") if Path(spec).exists() or ":" not in spec else spec.rsplit(":", 1)
    return path, (tuple(name.split(",")) if name else None)


def _knn_warning(bundle: Any, comps: dict[str, np.ndarray], failed: np.ndarray) -> dict[str, Any] | None:
    from invphys.evaluation.failure_score import measure
    from invphys.evaluation.ood import load_diagnostics, ood_settings

    s = ood_settings(load_diagnostics(bundle))
    if s["score"] != "knn" or s["threshold"] is None:
        return None
    return measure(comps["knn"], failed, np.nextafter(float(s["threshold"]), np.inf))


def main(argv: list[str] | None = None) -> int:
    from invphys.evaluation import failure_score as fs
    from invphys.evaluation.ood import auroc
    from invphys.inverter import load_inverter

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bundle", required=True)
    ap.add_argument("--calibration", required=True, help="FILE[:SET] of validated held-out answers")
    ap.add_argument("--report", nargs="*", default=[], help="FILE[:SET,...] sets to measure on")
    ap.add_argument("--method", help="whose answers (default: the bundle's default method)")
    ap.add_argument("--keep-training", action="store_true",
                    help="keep calibration rows whose true parameters are training rows (left out by default)")
    ap.add_argument("--rule", choices=("alarms", "recall"), default="alarms",
                    help="threshold rule: at most 10 %% - 1.5 SE false alarms on typical calibration answers "
                         "(default), or catch 80 %% of the failing ones")
    ap.add_argument("--write", action="store_true", help="store the model in the bundle's diagnostics")
    ap.add_argument("--out", help="write the results here (JSON)")
    args = ap.parse_args(argv)
    inv = load_inverter(args.bundle)
    method = args.method or inv.default_method
    model, comps = fs.fit_from_file(inv.bundle, args.calibration, method, keep_training=args.keep_training,
                                    rule=args.rule)
    cal_failed = comps.pop("failed")
    if str(Path(__file__).parent) not in sys.path:
        sys.path.insert(0, str(Path(__file__).parent))
    import _machine

    result: dict[str, Any] = {**_machine.provenance(), "bundle": args.bundle,
                              "device": f"fit on cpu ({_machine.cpu_name()}); R_actual of the answers from the files' "
                                        "simulator runs (the committed ones: one NVIDIA H200)",
                              "model": model, "sets": {},
                              "calibration_distant_5pct": _distant(model, comps, cal_failed)}
    for spec in args.report:
        rpath, rnames = _sets(spec)
        for name, s in fs.validated_answers(rpath, method, rnames).items():
            c = fs.components(inv.bundle, s["y"], s["theta"])
            p = fs.probability(model, c)
            result["sets"][name] = {"file": rpath, "warning": fs.measure(p, s["failed"], model["threshold"]),
                                    "auroc_each": {n: auroc(v, s["failed"]) for n, v in c.items()},
                                    "knn_warning": _knn_warning(inv.bundle, c, s["failed"]),
                                    "other_rule": _other_rule(p, s["failed"], model, comps, cal_failed)}
    text = json.dumps(result, indent=1, allow_nan=False, default=float)
    if args.out:
        Path(args.out).write_text(text + "\n")
    _print(result)
    if args.write:
        from invphys.evaluation.diagnose_report import write_failure_into_bundle

        print(f"stored in {write_failure_into_bundle(model, Path(args.bundle))}/calibration.json")
    return 0


def _other_rule(p: np.ndarray, failed: np.ndarray, model: dict[str, Any], cal_comps: dict[str, np.ndarray],
                cal_failed: np.ndarray) -> dict[str, Any]:
    """The same model at the threshold the other rule (recall or alarms) picks on the calibration rows."""
    from invphys.evaluation.failure_score import measure, probability, threshold

    other = "recall" if model["threshold_rule"]["rule"] == "alarms" else "alarms"
    thr, rule = threshold(probability(model, cal_comps), cal_failed, other)
    return {"threshold": thr, **rule, **measure(p, failed, thr)}


def _distant(model: dict[str, Any], comps: dict[str, np.ndarray], failed: np.ndarray) -> dict[str, Any]:
    """The warning on the 5 % of calibration rows farthest from the training data (``knn``); in-sample for
    the logistic model, not for the threshold rule's typical rows."""
    from invphys.evaluation.failure_score import measure, probability

    far = comps["knn"] >= np.quantile(comps["knn"], 0.95)
    p = probability(model, {k: v[far] for k, v in comps.items()})
    return measure(p, failed[far], model["threshold"])


def _print(result: dict[str, Any]) -> None:
    m = result["model"]
    c = m["calibration"]
    print(f"calibration: {c['n']} answers ({m['rows']['training_rows']} of the {m['rows']['given']} given were "
          f"training rows{'' if m['rows']['training_rows_used'] else ', left out'}), {c['failing']} "
          f"failing; threshold {m['threshold']:.3g}: recall {c['recall']:.3f}, alarms {c['alarm_rate']:.3f}, "
          f"AUROC {c['auroc']:.3f}")
    d = result["calibration_distant_5pct"]
    print(f"5 % most distant calibration rows: {d['failing']}/{d['n']} failing; recall {d['recall']:.3f}")
    for name, s in result["sets"].items():
        w, k = s["warning"], s["knn_warning"]
        print(f"{name}: {w['failing']}/{w['n']} failing; AUROC {w['auroc']:.3f} "
              f"({', '.join(f'{n} {v:.3f}' for n, v in s['auroc_each'].items())}); warning recall "
              f"{w['recall']:.3f}, alarms {w['alarm_rate']:.3f}; by the {s['other_rule']['rule']} rule: recall "
              f"{s['other_rule']['recall']:.3f}, alarms {s['other_rule']['alarm_rate']:.3f}"
              + (f"; knn warning: recall {k['recall']:.3f}, alarms {k['alarm_rate']:.3f}" if k else ""))


if __name__ == "__main__":
    raise SystemExit(main())
