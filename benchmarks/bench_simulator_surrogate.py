"""How learnable a stored simulator dataset is: held-out R^2 of the paper MLP and the shipped ensemble.

    python benchmarks/bench_simulator_surrogate.py datasets/orange_peel_paper \\
        --out benchmarks/results/simulator_surrogate_paper_v2.json

Split: 80/20 of the ok rows (seeded permutation). The held-out 20 % is used for R^2 only: every model
early-stops (keeps its best epoch) on ``--val-fraction`` of the TRAINING rows. Models:

* ``mlp_paper``: :class:`MLPSurrogate` with its (paper) defaults;
* ``mlp_new``: one network with the ensemble's defaults (SiLU, no batch norm/dropout, AdamW, one-cycle);
* ``ensemble``: :class:`EnsembleSurrogate` with its defaults (5 such networks), the shipped surrogate;
* ``ensemble_paper`` (``--paper-ensemble``): 5 paper MLPs (the ensemble before this change).

``--extra STORE`` (repeatable) adds the ok rows of other stores of the same simulator and features to the
TRAINING rows only (the held-out rows stay the main store's 20 %): more data, same test.

Learning curves (``--curve`` training-set sizes, same held-out rows) for ``mlp_paper`` and ``mlp_new``
(and ``ensemble`` with ``--curve-ensemble``).

``--transform NAME=KIND`` (repeatable) redefines a stored feature by a monotone map before training, as a
simulator that reported the feature in those units would; R^2 (``r2``, ``r2_per_feature``) is then measured
in the transformed units, which is what a feature so redefined would be judged on, and the JSON adds the
back-transformed predictions' R^2 in raw units (``r2_raw_units``, ...) and a ``transforms`` record. Kinds:

* ``log10``: ``log10(v)`` (every value must be > 0);
* ``log10_gain[:C]``: ``log10(v - C)``, the log of the excess over a fixed physical baseline C (every value
  must exceed C). Without ``:C`` only ``final_separation`` of an ``orange_peel`` store has a default: the
  centroid separation of the store preset's unsettled scene (skin dome against flesh, the same for every
  run; 0.0216 m for ``paper``). The redefinition proper would subtract each run's settled ``sep(0)``,
  which the stored data do not hold.

Without ``--transform`` nothing changes (same training targets, same JSON).

``--train-store STORE`` trains on the ok rows of STORE **instead of** the main store's training rows (e.g. an
adaptive design, ``dataset.adaptive``); the held-out rows stay the main store's split ``--seed`` (with
``--test-all``: every ok row of the main store, none of which was trained on). Learning curves then take
STORE's rows in generation order (``sample_index``: an adaptive design's initial rows, then its rounds).

``--ensemble-option KEY=VALUE`` (repeatable) changes a setting of ``ensemble`` (e.g. ``members=10``,
``hidden=[512,512,256]``, ``max_epochs=400``); the JSON records them under ``ensemble_options`` and in the
model's ``config``. An unknown key or a bad value fails as the plugin's config does.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# this tree's packages, unless the path lists them already (a device run may put an older copy first)
for _p in (str(ROOT), str(ROOT / "examples" / "orange_peel"), str(ROOT / "examples" / "anisompm"),):
    if _p not in sys.path:
        sys.path.insert(0, _p)

PAPER = {"activation": "relu", "batch_norm": True, "dropout": 0.1, "optimizer": "adam", "schedule": "constant",
         "lr": 1e-3, "max_epochs": 1000, "patience": 50}


def _models(seed: int, val: float, paper_ensemble: bool, ensemble_options: dict | None = None) -> dict:
    from invphys.plugins.surrogates.ensemble import EnsembleSurrogate
    from invphys.plugins.surrogates.mlp import MLPSurrogate

    new = EnsembleSurrogate.Config().model_dump(include={"activation", "batch_norm", "dropout", "optimizer",
                                                         "schedule", "lr", "max_epochs", "patience"})
    out = {
        "mlp_paper": lambda: MLPSurrogate(seed=seed, val_fraction=val),
        "mlp_new": lambda: MLPSurrogate(seed=seed, val_fraction=val, **new),
        "ensemble": lambda: EnsembleSurrogate(seed=seed, val_fraction=val, **(ensemble_options or {})),
    }
    if paper_ensemble:
        out["ensemble_paper"] = lambda: EnsembleSurrogate(seed=seed, val_fraction=val, **PAPER)
    return out


def split_rows(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(training, held-out) row indices: the seeded 80/20 split every model of this benchmark is scored on."""
    perm = np.random.default_rng(seed).permutation(n)
    return np.sort(perm[round(0.2 * n):]), np.sort(perm[: round(0.2 * n)])


def _scene_separation(identity: dict) -> float:
    """Centroid distance of skin and flesh in the preset's scene before settling (metres)."""
    from invphys_orange_peel.presets import get_preset
    from invphys_orange_peel.scene import build_scene

    return build_scene(get_preset(identity["preset"])).separation()


def same_kind_store(path: Path, main: Any, flag: str) -> Any:
    """The store at ``path``, refused unless its simulator, version, preset, config hash and features are
    ``main``'s (the backend may differ: the same physics)."""
    from invphys.core.dataset import DatasetStore

    other = DatasetStore(path)
    mine, theirs = (s.metadata.get("identity", {}) for s in (main, other))
    differ = [k for k in SAME_KIND if theirs.get(k) != mine.get(k)]
    if list(other.metadata.get("feature_names", [])) != list(main.metadata.get("feature_names", [])):
        differ.append("features")
    if differ:
        what = ", ".join(f"{k} {theirs.get(k)!r} (not {mine.get(k)!r})" if k != "features" else "other features"
                         for k in differ)
        raise SystemExit(f"{flag} {path}: not the same kind of runs as {main.path}: {what}")
    return other


#: identity fields two stores must share for rows of one to train a surrogate tested on the other
SAME_KIND = ("simulator", "version", "preset", "config")


def parse_options(items: list[str]) -> dict:
    """``KEY=VALUE`` strings -> a dict of YAML-parsed values (validated by the ensemble's own config)."""
    import yaml

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--ensemble-option {item!r}: expected KEY=VALUE")
        out[key] = yaml.safe_load(value)
    return out


def parse_transform(spec: str, names: list[str], identity: dict | None) -> tuple[str, dict]:
    """``NAME=KIND`` -> (name, record): ``kind``, ``offset`` C (0 for ``log10``), ``offset_source``."""
    name, sep, kind = spec.partition("=")
    if not sep or name not in names:
        raise SystemExit(f"--transform {spec!r}: expected NAME=KIND with NAME one of {', '.join(names)}")
    kind, colon, value = kind.partition(":")
    if kind == "log10" and not colon:
        return name, {"kind": "log10", "offset": 0.0, "offset_source": "none", "definition": "log10(v)"}
    if kind != "log10_gain":
        raise SystemExit(f"--transform {spec!r}: KIND is log10 or log10_gain[:C]")
    if colon:
        offset, source = float(value), "given constant (the same for every run)"
    elif name == "final_separation" and (identity or {}).get("simulator") == "orange_peel":
        offset = _scene_separation(identity)
        source = (f"separation of the unsettled {identity['preset']!r} scene (skin-dome and flesh centroids "
                  "before settling; the same for every run). A redefined feature would subtract each "
                  "run's settled sep(0), which the stored data do not hold")
    else:
        raise SystemExit(f"--transform {spec!r}: no default baseline for {name}; give log10_gain:C")
    return name, {"kind": "log10_gain", "offset": offset, "offset_source": source, "definition": "log10(v - C)"}


def forward(v: np.ndarray, rec: dict) -> np.ndarray:
    """The transformed feature (raises if a value is not above the offset)."""
    excess = np.asarray(v, dtype=np.float64) - rec["offset"]
    if not (excess > 0).all():
        raise SystemExit(f"{rec['kind']}: {int((excess <= 0).sum())} value(s) not above the offset {rec['offset']}")
    return np.log10(excess)


def inverse(u: np.ndarray, rec: dict) -> np.ndarray:
    """Raw units back from the transformed ones."""
    return rec["offset"] + 10.0 ** np.asarray(u, dtype=np.float64)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--val-fraction", type=float, default=0.1, help="early-stopping carve of the training rows")
    ap.add_argument("--curve", default="250,500,1000,1600")
    ap.add_argument("--curve-ensemble", action="store_true", help="also the ensemble's learning curve")
    ap.add_argument("--paper-ensemble", action="store_true", help="also 5 paper MLPs as an ensemble")
    ap.add_argument("--models", default="", help="comma-separated subset of the models to run")
    ap.add_argument("--extra", type=Path, action="append", default=[],
                    help="another store whose rows join the training rows only (repeatable)")
    ap.add_argument("--transform", action="append", default=[], metavar="NAME=KIND",
                    help="train and score feature NAME as log10 or log10_gain[:C] (repeatable; see above)")
    ap.add_argument("--ensemble-option", action="append", default=[], metavar="KEY=VALUE",
                    help="override a setting of the ensemble (YAML value, e.g. members=10, hidden=[512,512,256])")
    ap.add_argument("--train-store", type=Path, default=None,
                    help="train on this store's rows instead of the main store's training split")
    ap.add_argument("--train-first", type=int, default=None,
                    help="with --train-store: only its first N rows in generation order (sample_index)")
    ap.add_argument("--test-all", action="store_true",
                    help="with --train-store: score on every ok row of the main store")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if args.test_all and args.train_store is None:
        raise SystemExit("--test-all needs --train-store (else the main store's rows are trained on)")
    ensemble_options = parse_options(args.ensemble_option)

    import torch

    from invphys.core.dataset import DatasetStore
    from invphys.models.data import r2_scores

    store = DatasetStore(args.dataset)
    data = store.arrays(ok_only=True)
    names = list(data.feature_names)
    n = len(data.theta)
    tr, te = split_rows(n, args.seed)
    tt, yt, tv, yv = data.theta[tr], data.y[tr], data.theta[te], data.y[te]
    curve_order = None
    train_store_info = None
    if args.train_store is not None:
        other = same_kind_store(args.train_store, store, "--train-store")
        own = other.arrays(ok_only=True)
        tt, yt = own.theta, own.y
        curve_order = np.argsort(other.frame(ok_only=True)["sample_index"].to_numpy(), kind="stable")
        if args.train_first is not None:
            keep = curve_order[:args.train_first]
            tt, yt = tt[keep], yt[keep]
            curve_order = np.arange(len(keep))  # the kept rows are in generation order
        if args.test_all:
            tv, yv = data.theta, data.y
        train_store_info = {"dataset": str(args.train_store), "rows": len(tt), "first": args.train_first,
                            "fingerprint": own.fingerprint,
                            "test": "all main-store rows" if args.test_all else f"main-store split {args.seed}"}
    extra_info = []
    for path in args.extra:
        more = same_kind_store(path, store, "--extra")
        extra = more.arrays(ok_only=True)
        tt, yt = np.concatenate([tt, extra.theta]), np.concatenate([yt, extra.y])
        extra_info.append({"dataset": str(path), "rows": len(extra.theta), "fingerprint": extra.fingerprint,
                           "identity": more.metadata.get("identity")})
    transforms = dict(parse_transform(spec, names, store.metadata.get("identity")) for spec in args.transform)
    yv_raw = yv
    if transforms:
        yt, yv = yt.copy(), yv.copy()
        for name, rec in transforms.items():
            j = names.index(name)
            rec["raw_range"] = [float(min(yt[:, j].min(), yv[:, j].min())), float(max(yt[:, j].max(), yv[:, j].max()))]
            yt[:, j], yv[:, j] = forward(yt[:, j], rec), forward(yv[:, j], rec)
    out: dict = {
        "benchmark": "bench_simulator_surrogate",
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "command": "python benchmarks/bench_simulator_surrogate.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "dataset": str(args.dataset), "identity": store.metadata.get("identity"), "fingerprint": data.fingerprint,
        "n_train": len(tt), "n_test": len(tv), "val_fraction_of_train": args.val_fraction,
        "extra_training_stores": extra_info,
        **({"train_store": train_store_info} if train_store_info else {}),
        "feature_names": names,
        "machine": {"platform": platform.platform(), "device": "cpu", "torch": torch.__version__,
                    "threads_per_model": 1},
        "models": {},
    }
    if transforms:
        out["transforms"] = transforms
        out["r2_units"] = ("r2, r2_min_feature, r2_per_feature: transformed units for the transformed features "
                           "(raw for the rest); *_raw_units: predictions back-transformed, all raw units")
    if ensemble_options:
        out["ensemble_options"] = ensemble_options
    factories = _models(args.seed, args.val_fraction, args.paper_ensemble, ensemble_options)
    chosen = [m for m in args.models.split(",") if m] or list(factories)

    def save() -> None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=2))

    def run(label: str, rows: np.ndarray) -> dict:
        model = factories[label]()
        m = model.fit(tt[rows], yt[rows])
        pred = model.predict(tv)
        r2, per = r2_scores(yv, pred)
        res = {"r2": r2, "r2_min_feature": min(per), "r2_per_feature": dict(zip(names, per, strict=True)),
               "epochs": m["epochs"], "best_epoch": m["best_epoch"], "train_time_s": m["train_time_s"],
               "n_train": len(rows), "config": model.config.model_dump(mode="json")}
        if transforms:
            raw = np.array(pred, dtype=np.float64)
            for name, rec in transforms.items():
                raw[:, names.index(name)] = inverse(raw[:, names.index(name)], rec)
            r2_raw, per_raw = r2_scores(yv_raw, raw)
            res.update({"r2_raw_units": r2_raw, "r2_min_feature_raw_units": min(per_raw),
                        "r2_per_feature_raw_units": dict(zip(names, per_raw, strict=True))})
        return res

    for label in chosen:
        res = out["models"][label] = run(label, np.arange(len(tt)))
        print(f"{label}: R^2 {res['r2']:.4f} (min {res['r2_min_feature']:.3f}, {res['train_time_s']:.0f} s); "
              + ", ".join(f"{k} {v:.3f}" for k, v in res["r2_per_feature"].items()), flush=True)
        if transforms:
            print(f"{label} (raw units): R^2 {res['r2_raw_units']:.4f} (min {res['r2_min_feature_raw_units']:.3f}); "
                  + ", ".join(f"{k} {res['r2_per_feature_raw_units'][k]:.3f}" for k in transforms), flush=True)
        save()
    curves = [c for c in ("mlp_paper", "mlp_new") + (("ensemble",) if args.curve_ensemble else ()) if c in chosen]
    for label in curves:
        curve = []
        for size in (int(s) for s in args.curve.split(",")):
            size = min(size, len(tt))
            if size == len(tt):
                res = out["models"][label]
            else:
                order = curve_order if curve_order is not None else np.random.default_rng(100).permutation(len(tt))
                res = run(label, np.sort(order[:size]))
            curve.append({"n_train": size, "r2": res["r2"], "r2_min_feature": res["r2_min_feature"],
                          "r2_per_feature": res["r2_per_feature"]})
            print(f"curve {label} {size}: R^2 {res['r2']:.4f}", flush=True)
            out.setdefault("learning_curves", {})[label] = curve
            save()
    return out


if __name__ == "__main__":
    main()
