"""The ``train`` stage: fit the spec's surrogate and latent models on the dataset's train split.

Writes, under ``OUT/train/``:

* ``surrogate/`` and ``latent/<label>/``: the saved models (config, data fingerprint, metrics, weights);
* ``metrics.json`` and ``metrics.md``: held-out metrics of every model (the test split, 20 % by default);
* ``curves_surrogate.png``, ``curves_latent_<label>.png``: training curves; ``parity_surrogate.png``;

and the run's inverter bundle ``OUT/inverter/`` (surrogate, latent models, configured optimisers; the
invert stage adds the trained policies), see :mod:`invphys.inverter.writer`.

By default the held-out test split is also the validation set of every model (early stopping), as in
the paper's 80/20 protocol; ``dataset.early_stopping: training_carve`` makes each model carve its own
validation rows from the training split instead, so the held-out metrics are unbiased. :func:`train_models` is the same work without a runner context.
"""

from __future__ import annotations

import inspect
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.pipeline.cache import BUNDLE_SECTIONS

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("dataset", "surrogate", "latent_models")
#: what the bundle alone reads: a change rewrites the cached stage's bundle (:func:`refresh`), no re-run
REFRESHED_BY: tuple[str, ...] = BUNDLE_SECTIONS


def refresh(ctx: StageContext) -> bool:
    """Rewrite the run's bundle from the trained models, unless the invert stage has finished (its
    bundle, with the policies, is the run's then; it refreshes it itself). True when rewritten."""
    from invphys.pipeline.artifacts import write_inverter

    if ctx.finished("invert"):
        return False
    write_inverter(ctx, with_policies=False)
    return True

METRICS_JSON = "metrics.json"
METRICS_MD = "metrics.md"


def run(ctx: StageContext) -> dict[str, Any]:
    """Train and save every model of the spec; returns the metrics summary."""
    spec = ctx.spec
    if spec.surrogate is None:
        raise InvphysError("the train stage needs a 'surrogate' block in the spec (e.g. {type: mlp})")
    data = ctx.dataset()
    train_idx, test_idx = ctx.split()
    summary = train_models(
        theta=data.theta, y=data.y, train_idx=train_idx, test_idx=test_idx,
        surrogate=dict(spec.surrogate), latent_models={k: dict(v) for k, v in spec.latent_models.items()},
        out=ctx.stage_dir, registry=ctx.registry, seed=ctx.seed, progress=ctx.progress,
        feature_names=list(data.feature_names), param_names=list(data.param_names),
        dataset_fingerprint=data.fingerprint, log=ctx.log, tracker=ctx.tracker.scoped("train"),
        early_stop_on_held_out=spec.dataset.early_stopping == "held_out",
    )
    from invphys.pipeline.artifacts import write_inverter

    summary["inverter"] = write_inverter(ctx, with_policies=False)
    return summary


def train_models(theta: np.ndarray, y: np.ndarray, train_idx: np.ndarray, test_idx: np.ndarray,
                 surrogate: dict[str, Any] | None, latent_models: dict[str, dict[str, Any]], out: str | Path,
                 registry: Any = None, seed: int = 0, progress: bool = False,
                 feature_names: list[str] | None = None, param_names: list[str] | None = None,
                 dataset_fingerprint: str | None = None, log: Any = None, tracker: Any = None,
                 early_stop_on_held_out: bool = True) -> dict[str, Any]:
    """Fit, evaluate on ``test_idx`` and save the surrogate and each latent model under ``out``.

    ``surrogate`` and each ``latent_models`` value are plugin blocks ``{"type": name, **config}``; a
    block without ``seed`` gets ``seed``. Returns the summary (also written as ``metrics.json``).
    ``tracker`` receives the per-epoch curves under ``surrogate/`` and ``latent_models/<label>/``.
    ``early_stop_on_held_out=False``: the models never see the ``test_idx`` rows while fitting (each
    carves its own validation rows from ``train_idx``).
    """
    from invphys import registry as registry_module
    from invphys.models.data import r2_scores
    from invphys.models.plots import plot_curves, plot_parity

    reg = registry or registry_module.default_registry()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    theta = np.asarray(theta, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    train_idx, test_idx = np.asarray(train_idx), np.asarray(test_idx)
    if len(train_idx) == 0 or len(test_idx) == 0:
        raise InvphysError("the train stage needs non-empty train and test splits")
    fnames = list(feature_names) if feature_names else [f"y{j}" for j in range(y.shape[1])]
    pnames = list(param_names) if param_names else [f"theta{j}" for j in range(theta.shape[1])]
    tt, yt, tv, yv = theta[train_idx], y[train_idx], theta[test_idx], y[test_idx]
    info = {"feature_names": fnames, "param_names": pnames, "dataset_fingerprint": dataset_fingerprint,
            "n_train": len(train_idx), "n_test": len(test_idx),
            "early_stopping": "held_out" if early_stop_on_held_out else "training_carve"}
    say = log or (lambda message: None)
    summary: dict[str, Any] = {"n_train": len(train_idx), "n_test": len(test_idx),
                               "dataset_fingerprint": dataset_fingerprint, "feature_names": fnames,
                               "early_stopping": info["early_stopping"], "surrogate": None, "latent_models": {}}
    sur = None
    if surrogate is not None:
        sur = _create(reg, "surrogate", surrogate, seed, "surrogate")
        sur.info = {**getattr(sur, "info", {}), **info}
        say(f"training surrogate {sur.name!r} on {len(tt)} rows")
        _fit(sur, tt, yt, (tv, yv) if early_stop_on_held_out else None, progress, _scope(tracker, "surrogate"))
        pred = sur.predict(tv)
        r2, per = r2_scores(yv, pred)
        _, std = sur.predict_with_uncertainty(tv)
        entry = {"type": sur.name, "r2": r2, "r2_per_feature": dict(zip(fnames, per, strict=True)),
                 "mean_std": float(np.mean(std / np.where(yv.std(0) > 0, yv.std(0), 1.0))),
                 "path": "surrogate", "metrics": sur.metrics}
        sur.save(out / "surrogate")
        summary["surrogate"] = entry
        if getattr(sur, "history", None):
            plot_curves(sur.history, out / "curves_surrogate.png", f"surrogate {sur.name}")
        plot_parity(yv, pred, fnames, out / "parity_surrogate.png", f"surrogate {sur.name}: held-out parity")
        say(f"surrogate {sur.name!r}: held-out R^2 {r2:.3f}")
    for label, block in latent_models.items():
        lat = _create(reg, "latent_model", block, seed, f"latent_models.{label}")
        lat.info = {**getattr(lat, "info", {}), **info, "label": label}
        say(f"training latent model {label!r} ({lat.name}) on {len(tt)} rows")
        _fit(lat, tt, yt, (tv, yv) if early_stop_on_held_out else None, progress,
             _scope(tracker, f"latent_models/{label}"))
        z = lat.encode(tv)
        rec = lat.decode(z)
        entry = {"type": lat.name, "latent_dim": lat.latent_dim, "recon_mse": float(((rec - tv) ** 2).mean()),
                 "in_bounds_fraction": float((np.abs(z) <= lat.latent_bound).all(axis=1).mean()),
                 "path": f"latent/{label}", "metrics": lat.metrics}
        try:
            entry["head_r2"] = r2_scores(yv, lat.predict_features(z))[0]
        except NotImplementedError:
            entry["head_r2"] = None
        if sur is not None:  # the paper's decode-then-evaluate path on held-out parameters
            entry["shared_r2_after_roundtrip"] = r2_scores(yv, sur.predict(rec))[0]
        lat.save(out / "latent" / label)
        summary["latent_models"][label] = entry
        if getattr(lat, "history", None):
            plot_curves(lat.history, out / f"curves_latent_{label}.png", f"latent {label} ({lat.name})")
        head = "n/a" if entry["head_r2"] is None else f"{entry['head_r2']:.3f}"
        say(f"latent {label!r}: recon MSE {entry['recon_mse']:.4f}, head R^2 {head}")
    (out / METRICS_JSON).write_text(json.dumps(summary, indent=2, default=float))
    (out / METRICS_MD).write_text(metrics_markdown(summary))
    return summary


def _create(reg: Any, kind: str, block: dict[str, Any], seed: int, where: str) -> Any:
    from pydantic import ValidationError

    from invphys.core.errors import SpecError

    block = dict(block)
    if not block.get("type"):
        raise SpecError(f"{where}: a plugin block needs a 'type' field")
    cls = reg.get(kind, block["type"])
    fields = getattr(getattr(cls, "Config", None), "model_fields", {})
    if "seed" in fields and "seed" not in block:
        block["seed"] = seed
    try:
        return reg.create(kind, block)
    except ValidationError as exc:
        problems = "; ".join(f"{where}.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise SpecError(problems) from None


def _fit(model: Any, tt: np.ndarray, yt: np.ndarray, validation: tuple[np.ndarray, np.ndarray] | None,
         progress: bool, tracker: Any = None) -> None:
    """Fit with ``validation`` (None: the model's own carve) and the tracker, when ``fit`` accepts them."""
    accepted = inspect.signature(model.fit).parameters
    extra: dict[str, Any] = {}
    if "validation" in accepted and validation is not None:
        extra["validation"] = validation
    if "tracker" in accepted and tracker is not None:
        extra["tracker"] = tracker
    model.fit(tt, yt, progress=progress, **extra)


def _scope(tracker: Any, prefix: str) -> Any:
    return None if tracker is None else tracker.scoped(prefix)


def metrics_markdown(summary: dict[str, Any]) -> str:
    """The summary as markdown tables: surrogate R^2 per feature, latent-model metrics."""
    stop = {"held_out": "early stopping on the held-out rows (the paper's protocol)",
            "training_carve": "early stopping on carves of the training rows"}.get(summary.get("early_stopping", ""), "")
    lines = [f"# Training metrics\n\n{summary['n_train']} training rows, {summary['n_test']} held-out rows"
             f"{'; ' + stop if stop else ''}.\n"]
    s = summary.get("surrogate")
    if s:
        lines += [f"## Surrogate `{s['type']}`\n", f"Held-out R²: **{s['r2']:.4f}** (mean over features)\n",
                  "| feature | R² |", "|---|---|"]
        lines += [f"| {k} | {v:.4f} |" for k, v in s["r2_per_feature"].items()]
        lines.append("")
    if summary.get("latent_models"):
        lines += ["## Latent models\n",
                  "| label | type | k | recon MSE | head R² | shared R² after round trip | in [-3,3]^k |",
                  "|---|---|---|---|---|---|---|"]
        for label, e in summary["latent_models"].items():
            head = "n/a" if e.get("head_r2") is None else f"{e['head_r2']:.4f}"
            shared = e.get("shared_r2_after_roundtrip")
            shared_s = "n/a" if shared is None else f"{shared:.4f}"
            lines.append(f"| {label} | {e['type']} | {e['latent_dim']} | {e['recon_mse']:.4f} | {head} | "
                         f"{shared_s} | {e['in_bounds_fraction']:.3f} |")
        lines.append("")
    return "\n".join(lines)
