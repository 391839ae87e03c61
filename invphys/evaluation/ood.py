"""Is a target like the ones a bundle was trained on? Per-target out-of-distribution scores.

Candidate scores (larger: more unusual), each measured by ``invphys diagnose`` for how well it ranks
failing answers on held-out rows (AUROC):

* ``knn``: mean distance to the :data:`K` nearest training rows in standardised feature space
  (over the features a target gives);
* ``misfit``: 1 - R_surr of the answer (the surrogate cannot reproduce the target: misspecification);
* ``ensemble_std``: the surrogate ensemble's normalised disagreement at the answer;
* ``outside_fraction``: the share of the posterior's raw draws that fell outside the parameter box;
* ``posterior_std``: the posterior draws' mean std per parameter (normalised units).

The diagnostics keep the best-ranking score and a threshold (the held-out rows' 90 % quantile, so the
warning fires on about 10 % of typical targets): :func:`ood_score` and :func:`ood_threshold` read them.
Features from another simulator are refused by name (:class:`FeatureMismatch`), never scored. Whether an
*answer* will fail on the simulator is scored by :mod:`invphys.evaluation.failure_score`, which answers use
instead where a bundle holds its model.
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from typing import Any

import numpy as np

from invphys.core.user_targets import TargetError, UserTargets, from_array, from_mappings

K = 10
SCORES: tuple[str, ...] = ("knn", "misfit", "ensemble_std", "outside_fraction", "posterior_std")
#: scores that need the answer (``answers``) or the posterior draws (``draws``)
NEEDS: dict[str, str] = {"misfit": "answers", "ensemble_std": "answers", "outside_fraction": "draws",
                         "posterior_std": "draws"}
_TREES: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()
#: per bundle: its standardised finite training rows and their indices (:func:`standardised_train`)
_TRAIN: weakref.WeakKeyDictionary[Any, tuple[np.ndarray, np.ndarray]] = weakref.WeakKeyDictionary()


class FeatureMismatch(TargetError):
    """A target names features the bundle does not predict (another simulator's features)."""


def feature_targets(bundle: Any, targets: Any) -> UserTargets:
    """``targets`` (UserTargets, a mapping or list of mappings by feature name, or an array in the
    bundle's feature order) checked against the bundle's features; foreign names raise FeatureMismatch."""
    names = tuple(bundle.feature_names)
    if isinstance(targets, UserTargets):
        if tuple(targets.feature_names) != names:
            raise _mismatch(bundle, targets.feature_names)
        return targets
    rows = [targets] if isinstance(targets, Mapping) else targets
    if isinstance(rows, list) and rows and all(isinstance(r, Mapping) for r in rows):
        given = {str(k) for r in rows for k in r if str(k) not in ("id", "label", "name")}
        if given - set(names):
            raise _mismatch(bundle, sorted(given))
        return from_mappings(rows, names, partial=True, source="target")
    arr = np.asarray(targets, dtype=np.float64)
    if arr.shape[-1] != len(names):
        raise FeatureMismatch(f"targets have {arr.shape[-1]} features, bundle {bundle.root} predicts {len(names)} "
                              f"({', '.join(names)}): features of another simulator?")
    return from_array(arr, names)


def _mismatch(bundle: Any, given: Any) -> FeatureMismatch:
    names = tuple(bundle.feature_names)
    foreign = [n for n in given if n not in names]
    sim = bundle.manifest.get("simulator", {})
    return FeatureMismatch(f"feature mismatch: {', '.join(foreign) or 'the feature order'} are not features of "
                           f"bundle {bundle.root} (simulator {sim.get('name')} {sim.get('version')}; its features: "
                           f"{', '.join(names)}): features from another simulator cannot be scored or inverted")


def knn_distance(bundle: Any, t: UserTargets, k: int = K, leave_identical: bool = False) -> np.ndarray:
    """(B,) mean distance to the ``k`` nearest training rows, standardised, over each target's given
    features (scaled to all features: distance x sqrt(M / given)). ``leave_identical``: training rows
    identical to the target (distance 0) are left out (a target that is itself a training row)."""
    dist, _ = neighbours(bundle, t, k, leave_identical)
    return dist.mean(axis=1)


def neighbours(bundle: Any, t: UserTargets, k: int, leave_identical: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(distances (B, k) scaled to all features, indices (B, k) into the bundle's finite training rows) of
    each target's ``k`` nearest training rows in standardised space, over the features it gives."""
    train, _ = standardised_train(bundle)
    k = min(k, len(train) - int(leave_identical))
    extra = 1 if leave_identical else 0
    z = (np.nan_to_num(t.values) - _feature_stats(bundle)[0]) / _feature_stats(bundle)[1]
    dist, idx = np.empty((len(t), k)), np.empty((len(t), k), dtype=np.int64)
    for pattern in {tuple(m) for m in t.mask.tolist()}:
        sel = np.all(t.mask == np.array(pattern), axis=1)
        cols = np.flatnonzero(pattern)
        tree = _tree(bundle, tuple(cols.tolist()), train[:, cols])
        d, i = tree.query(z[sel][:, cols], k=k + extra)
        d, i = np.asarray(d).reshape(int(sel.sum()), -1), np.asarray(i).reshape(int(sel.sum()), -1)
        if extra:  # drop one identical row where there is one, else the farthest of the k + 1
            same = d[:, :1] == 0.0
            d = np.where(same, d[:, 1:], d[:, :-1])
            i = np.where(same, i[:, 1:], i[:, :-1])
        dist[sel], idx[sel] = d * np.sqrt(len(pattern) / len(cols)), i
    return dist, idx


def _feature_stats(bundle: Any) -> tuple[np.ndarray, np.ndarray]:
    feats = bundle.manifest["features"]
    return np.asarray(feats["mean"], dtype=np.float64), np.asarray(feats["std"], dtype=np.float64)


def standardised_train(bundle: Any) -> tuple[np.ndarray, np.ndarray]:
    """(standardised features of the bundle's finite training rows, their indices in ``data("train")``),
    computed once per bundle (read-only arrays: every target's score reads them)."""
    if bundle not in _TRAIN:
        mean, std = _feature_stats(bundle)
        train = (bundle.data("train")[1] - mean) / std
        keep = np.flatnonzero(np.all(np.isfinite(train), axis=1))
        rows = train[keep]
        for a in (rows, keep):
            a.setflags(write=False)
        _TRAIN[bundle] = (rows, keep)
    return _TRAIN[bundle]


def _tree(bundle: Any, cols: tuple[int, ...], data: np.ndarray) -> Any:
    from scipy.spatial import cKDTree

    trees = _TREES.setdefault(bundle, {})
    if cols not in trees:
        trees[cols] = cKDTree(data)
    return trees[cols]


def score_components(bundle: Any, targets: Any, answers: np.ndarray | None = None, draws: Any = None,
                     names: tuple[str, ...] = SCORES) -> dict[str, np.ndarray]:
    """Every score of ``names`` that the inputs allow: ``answers`` (B, d) normalised parameters of the
    answers, ``draws`` a :class:`~invphys.inverter.draws.PosteriorDraws` (or anything with ``samples``
    and ``outside_fraction``)."""
    from invphys.core.masked_recovery import masked_recovery
    from invphys.evaluators.uncertainty import normalised_std

    t = feature_targets(bundle, targets)
    out: dict[str, np.ndarray] = {}
    if "knn" in names:
        out["knn"] = knn_distance(bundle, t)
    if answers is not None and {"misfit", "ensemble_std"} & set(names):
        mean, std = bundle.surrogate.predict_with_uncertainty(np.atleast_2d(answers))
        out["misfit"] = 1.0 - masked_recovery(mean, np.nan_to_num(t.values), bundle.scales, t.mask, bundle.kappa)
        out["ensemble_std"] = normalised_std(std, bundle.scales)
    if draws is not None:
        out["outside_fraction"] = np.asarray(draws.outside_fraction, dtype=np.float64)
        out["posterior_std"] = np.asarray(draws.samples, dtype=np.float64).std(axis=1).mean(axis=1)
    return {n: out[n] for n in names if n in out}


def ood_settings(diagnostics: dict[str, Any] | None) -> dict[str, Any]:
    """The stored OOD block (score name, threshold, ...), or the default ``knn`` with no threshold."""
    block = (diagnostics or {}).get("ood") or {}
    return {"score": block.get("score", "knn"), "threshold": block.get("threshold"), **block}


def ood_score(bundle: Any, targets: Any, answers: np.ndarray | None = None, draws: Any = None,
              diagnostics: dict[str, Any] | None = None) -> np.ndarray:
    """(B,) the bundle's chosen OOD score of each target (larger: more unusual); its diagnostics choose
    the score (default ``knn``, which needs nothing but the targets)."""
    name = ood_settings(diagnostics if diagnostics is not None else load_diagnostics(bundle))["score"]
    need = NEEDS.get(name)
    if need and (answers if need == "answers" else draws) is None:
        raise TargetError(f"the OOD score {name!r} of bundle {bundle.root} needs the {need}")
    return score_components(bundle, targets, answers, draws, names=(name,))[name]


def ood_threshold(bundle: Any, diagnostics: dict[str, Any] | None = None) -> float | None:
    """The warning threshold of :func:`ood_score` (None: the bundle holds no diagnostics)."""
    t = ood_settings(diagnostics if diagnostics is not None else load_diagnostics(bundle))["threshold"]
    return None if t is None else float(t)


def load_diagnostics(bundle: Any) -> dict[str, Any] | None:
    """The numbers answers use (``diagnostics/calibration.json`` of the bundle), or None."""
    from invphys.core.safe_read import UserFileError, load_user_json

    path = bundle.root / "diagnostics" / "calibration.json"
    if not path.is_file():
        return None
    try:
        data = load_user_json(path, what="bundle diagnostics")
    except UserFileError:
        data = None
    if not isinstance(data, dict):
        raise TargetError(f"bundle {bundle.root}: {path.name} in diagnostics/ is not a JSON object; "
                          f"run invphys diagnose {bundle.root} --write again")
    return data


def auroc(score: np.ndarray, failed: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` ranking ``failed`` rows above the others (ties count half;
    NaN without both kinds of row)."""
    from scipy.stats import rankdata

    s = np.asarray(score, dtype=np.float64)
    f = np.asarray(failed, dtype=bool)
    ok = np.isfinite(s)
    s, f = s[ok], f[ok]
    n1, n0 = int(f.sum()), int((~f).sum())
    if n1 == 0 or n0 == 0:
        return float("nan")
    r = rankdata(s)
    return float((r[f].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))
