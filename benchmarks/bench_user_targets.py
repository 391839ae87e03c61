"""User-like recovery: a bundle's answers to fresh simulations it never saw, validated on the simulator.

    python benchmarks/bench_user_targets.py --bundle inverters/orange_peel_paper \\
        --targets uniform=datasets/orange_peel_paper_fresh_uniform edge=datasets/orange_peel_paper_fresh_edge \\
        --all-data datasets/orange_peel_paper datasets/orange_peel_paper_adaptive \\
                   datasets/orange_peel_paper_adaptive_seed3 datasets/orange_peel_paper_seed1_v030 \\
        --methods npe_best64 lookup --validate --out benchmarks/results/user_targets_paper.json

The evaluation protocol's user-like sets (docs/evaluation.md): each target store holds fresh simulations
(true parameters and features); every answer goes through the user's path (``Inverter.invert_many``, then
``Inverter.validate``: the bundle's recorded simulator re-runs it), next to

* ``nearest_neighbour_all``: a 1-NN lookup (R_gt metric) over ALL the rows the ``--all-data`` stores hold
  except the targets' own rows (the baseline every answer must beat); its answers are stored rows, so their
  real R is known without re-simulating them (``stored_rows``, also without ``--validate`` on a CPU; with
  ``--validate`` their stored features are their R_actual: they are not re-simulated), and
* ``truth``: the targets' own parameters re-simulated (the noise floor).

Per set and method: mean R_actual with a bootstrap 95 % interval, the worst answer, the paired difference
against ``nearest_neighbour_all``, and how the answers' warnings rank failures (R_actual < 0.8): recall on
failing targets and the alarm rate on the others. Without ``--validate`` only the surrogate's R is scored
(no simulator: a quick check of the plumbing). Every method also gets its mean absolute parameter error
against the truth (normalised units; ``theta_error``) and its answer time per target.

Answering and simulating can run on different machines (the answers need sbi, the simulation a GPU)::

    python benchmarks/bench_user_targets.py --bundle inverters/orange_peel_paper_all --targets ... \
        --methods pool npe_best64 --label all --answers-out runs/answers_all.json --out runs/surr_all.json
    python benchmarks/bench_user_targets.py --bundle inverters/orange_peel_paper --targets ... \
        --answers-in runs/answers_all.json runs/answers_shipped.json --all-data ... --validate --out ...

``--answers-out`` writes every answer's normalised parameters (and warnings) per set and method;
``--answers-in`` answers nothing: it re-scores (and with ``--validate`` re-simulates) the answers of one
or more such files, every file's methods named ``LABEL:METHOD`` when it was written with ``--label``.
All answers are scored with ``--bundle``'s scales and simulator, whichever bundle gave them.

A set may be the held-out rows of a store: ``NAME=STORE@KEYFILE`` keeps the rows whose keys the file lists
(one per line, ``#`` comments), e.g. ``heldout=datasets/orange_peel_paper_seed1_v030@inverters/specs/
orange_peel_paper_all.heldout_keys.txt``. ``--per-target-out FILE`` writes every target's answer, R_actual and
R_surrogate per set and method (what a failure warning is fitted and checked on); ``--no-truth`` skips the truth.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

FAIL_BELOW = 0.8


def _machine() -> Any:
    """The benchmarks' shared ``_machine`` helpers (this script may be loaded by file, as the tests do)."""
    if str(Path(__file__).parent) not in sys.path:
        sys.path.insert(0, str(Path(__file__).parent))
    import _machine

    return _machine


def _device() -> str:
    try:
        import torch

        if torch.cuda.is_available():
            return torch.cuda.get_device_name(0)
    except ImportError:
        pass
    return f"cpu ({_machine().cpu_name()})"


def _read_keys(path: str) -> list[str]:
    """Row keys, one per line (``#`` comments and blank lines skipped)."""
    lines = (ln.strip() for ln in Path(path).read_text().splitlines())
    return [ln for ln in lines if ln and not ln.startswith("#")]


def _store_rows(path: str) -> Any:
    """The ok rows of a store; ``STORE@KEYFILE``: only the rows whose keys the file lists (held-out rows)."""
    from invphys.core.dataset import DatasetStore

    store, _, key_file = path.partition("@")
    arrays = DatasetStore(store).arrays(ok_only=True)
    if key_file:
        wanted = set(_read_keys(key_file))
        keep = np.array([k in wanted for k in arrays.keys], dtype=bool)
        arrays.theta, arrays.y, arrays.keys = arrays.theta[keep], arrays.y[keep], arrays.keys[keep]
    if len(arrays.y) == 0:
        raise SystemExit(f"error: {path} holds no successful rows")
    return arrays


def _lookup_all(inv: Any, stores: list[str], targets: np.ndarray,
                exclude_keys: Any = ()) -> tuple[np.ndarray, np.ndarray, int]:
    """1-NN over every row the stores hold (same parameter and feature names as the bundle), except the
    rows whose keys are in ``exclude_keys`` (the targets themselves, when they are rows of those stores):
    the chosen rows' parameters, their stored (really simulated) features, and how many rows were searched."""
    from invphys.plugins.baselines.nearest_neighbour import NearestNeighbour

    blocks = [_store_rows(s) for s in stores]
    for s, a in zip(stores, blocks, strict=True):
        if tuple(a.feature_names) != inv.feature_names or tuple(a.param_names) != inv.parameter_names:
            raise SystemExit(f"error: {s} holds other parameters or features than the bundle")
    excluded = set(exclude_keys)
    keep = np.concatenate([[k not in excluded for k in a.keys] for a in blocks]).astype(bool)
    theta = np.concatenate([a.theta for a in blocks])[keep]
    y = np.concatenate([a.y for a in blocks])[keep]
    nn = NearestNeighbour({"k": 1, "metric": "r_gt"})
    nn.fit(theta, y, inv.bundle.scales)
    ans = nn.answer(targets)
    rows = np.asarray(ans.info["rows"])[:, 0]  # the nearest row of each target: the answer
    return ans.theta, y[rows], len(theta)


def _with_stored(inv: Any, result: Any, features: np.ndarray) -> Any:
    """``result`` (an answer that is a stored row) with the row's real features and their R against the
    target (``r_known``): the lookup's R without re-simulating it."""
    from invphys.core.masked_recovery import masked_recovery

    best = result.best
    best.known = np.asarray(features, dtype=np.float64)
    best.r_known = float(masked_recovery(best.known[None], result.target, inv.bundle.scales, result.mask,
                                         inv.bundle.kappa)[0])
    return result


def _invert(inv: Any, y: np.ndarray, method: str, seed: int) -> list[Any]:
    """``invert_many`` with ``method``; ``POOL:KEY=VALUE,...`` is a pool (``pool`` or a bundle's pool entry, e.g.
    ``pool_nsf4``) with other settings (e.g. ``pool:lam=0,moves=0``, ``pool_nsf4:exact=false``; they win over an
    entry's own settings, the entry's others stay), so that variants are answered, and validated, side by side."""
    name, _, opts = method.partition(":")
    if not opts or not _is_pool(inv, name):
        return list(inv.invert_many(y, method=method, seed=seed))
    from invphys.inverter.pool import PoolSettings

    kw = {k: _pool_value(k, v) for k, v in (o.split("=", 1) for o in opts.split(","))}
    entry = inv.bundle.methods.get(name)  # None for the built-in pool
    own = None if entry is None else entry.get("config")
    default = inv.pool_settings
    if entry is None:
        inv.pool_settings = PoolSettings().with_(**kw)
    else:  # checked with the entry's own settings (a margin needs the entry's exact)
        entry["config"] = {**(own or {}), **{k: list(v) if isinstance(v, tuple) else v for k, v in kw.items()}}
    try:
        return list(inv.invert_many(y, method=name, seed=seed))
    finally:
        inv.pool_settings = default
        if entry is not None:
            entry["config"] = own


def _is_pool(inv: Any, name: str) -> bool:
    from invphys.inverter.pool import POOL_METHOD

    return name == POOL_METHOD or (inv.bundle.methods.get(name) or {}).get("type") == POOL_METHOD


def _pool_value(key: str, text: str) -> Any:
    """A ``pool:KEY=VALUE`` setting's value, parsed by the type of :class:`PoolSettings`' field (``extra``: names
    joined by ``+``)."""
    import dataclasses

    from invphys.inverter.pool import PoolSettings

    kinds = {f.name: str(f.type) for f in dataclasses.fields(PoolSettings)}
    kind = kinds.get(key)
    if kind is None:
        raise SystemExit(f"error: unknown pool setting {key!r} (settings: {', '.join(kinds)})")
    if kind == "bool":
        return text.strip().lower() in ("1", "true", "yes")
    if kind.startswith("tuple"):
        return tuple(t for t in text.split("+") if t)
    return {"int": int, "float": float}.get(kind, str)(text)


def _answers(inv: Any, arrays: Any, methods: list[str], all_data: list[str], seed: int,
             given: dict[str, Any] | None = None, timing: dict[str, float] | None = None,
             with_truth: bool = True) -> dict[str, list[Any]]:
    """InversionResults per method label for every target of one set: answered by ``inv``, or (``given``:
    {label: {"theta": ..., "warnings": ...}}) re-scored from an answers file."""
    y = arrays.y
    out: dict[str, list[Any]] = {}
    for m in methods:
        t0 = time.perf_counter()
        out[m] = _invert(inv, y, m, seed)
        dt = time.perf_counter() - t0
        if timing is not None:
            timing[m] = 1e3 * dt / max(len(y), 1)
        print(f"  {m}: {len(y)} answers in {dt:.2f} s", file=sys.stderr)
    for m, rec in (given or {}).items():
        theta = np.asarray(rec["theta"], dtype=np.float64)
        if theta.shape != (len(y), len(inv.parameter_names)):
            raise SystemExit(f"error: answers of {m!r} hold {theta.shape} parameters for {len(y)} targets")
        out[m] = [inv.evaluate(theta=t, target=v, label=m) for t, v in zip(theta, y, strict=True)]
        for r, w in zip(out[m], rec.get("warnings") or [[]] * len(y), strict=True):
            r.warnings = list(w)
    if all_data:
        theta_nn, y_nn, _ = _lookup_all(inv, all_data, y, exclude_keys=arrays.keys)
        out["nearest_neighbour_all"] = [
            _with_stored(inv, inv.evaluate(theta=t, target=v, label="nearest_neighbour_all"), f)
            for t, v, f in zip(theta_nn, y, y_nn, strict=True)]
    if with_truth:
        out["truth"] = [inv.evaluate(theta=t, target=v, label="truth") for t, v in zip(arrays.theta, y, strict=True)]
    return out


def _score(results: list[Any], validated: bool) -> np.ndarray:
    """R per answer: the surrogate's without ``--validate``; validated, the re-simulated R, or for an answer
    that is a stored row and was not re-simulated, its stored features' R (a real simulation too)."""
    if not validated:
        return np.array([r.r_surrogate for r in results], dtype=np.float64)
    return np.array([_real_r(r) for r in results], dtype=np.float64)


def _real_r(result: Any) -> float:
    if result.r_actual is not None:
        return float(result.r_actual)
    return 0.0 if result.r_known is None else float(result.r_known)


def _to_simulate(answers: dict[str, list[Any]]) -> list[Any]:
    """The answers ``--validate`` re-simulates: all but the stored rows (their R is already a simulator's)."""
    return [r for res in answers.values() for r in res if r.r_known is None]


#: the out-of-distribution warning of a bundle with diagnostics (invphys.inverter.diagnosed)
OOD_WARNING = ("unusual target", "may not reproduce the target")


def _recall(warned: np.ndarray, failing: np.ndarray) -> dict[str, Any]:
    return {"warned": int(warned.sum()),
            "recall_on_failing": float(warned[failing].mean()) if failing.any() else None,
            "alarm_rate_on_others": float(warned[~failing].mean()) if (~failing).any() else None}


def _warning_rank(results: list[Any], r: np.ndarray) -> dict[str, Any]:
    """How warnings rank failing answers (R < FAIL_BELOW): any warning (every posterior answer notes its
    unidentified parameters), and the out-of-distribution warning alone."""
    failing = r < FAIL_BELOW
    return {"failing": int(failing.sum()),
            "any": _recall(np.array([bool(res.warnings) for res in results]), failing),
            "out_of_distribution": _recall(np.array([any(p in w for p in OOD_WARNING for w in res.warnings)
                                                     for res in results]), failing)}


def _stored_summary(known: np.ndarray) -> dict[str, Any]:
    """How many answers are stored rows, and their real R (with a bootstrap interval when every answer is)."""
    from invphys.evaluation.stats import bootstrap_mean_ci

    ok = np.isfinite(known)
    out: dict[str, Any] = {"n": int(ok.sum()), "r_mean": float(known[ok].mean())}
    if ok.all():
        _, lo, hi = bootstrap_mean_ci(known)
        out["r_ci95"], out["r_worst"] = [float(lo), float(hi)], float(known.min())
    return out


def _stored_text(stored: dict[str, Any] | None) -> str:
    if not stored:
        return ""
    ci = stored.get("r_ci95")
    interval = f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else ""
    return f"; {stored['n']} stored rows, real R {stored['r_mean']:.3f}{interval}"


def summarise(answers: dict[str, list[Any]], validated: bool, reference: str = "nearest_neighbour_all",
              truth_theta: np.ndarray | None = None) -> dict[str, Any]:
    from invphys.evaluation.stats import bootstrap_mean_ci, paired_difference

    scores = {m: _score(res, validated) for m, res in answers.items()}
    out: dict[str, Any] = {}
    for m, r in scores.items():
        _, lo, hi = bootstrap_mean_ci(r)
        row: dict[str, Any] = {"n": len(r), "r_mean": float(np.mean(r)), "r_ci95": [float(lo), float(hi)],
                               "r_worst": float(np.min(r)), "below_0_8": int(np.sum(r < FAIL_BELOW)),
                               "r_surrogate_mean": float(np.mean([x.r_surrogate for x in answers[m]]))}
        known = np.array([np.nan if x.r_known is None else x.r_known for x in answers[m]], dtype=np.float64)
        if np.isfinite(known).any():  # answers that are stored rows: their real R, no re-simulation needed
            row["stored_rows"] = _stored_summary(known)
        if truth_theta is not None:
            err = np.abs(np.array([x.theta for x in answers[m]]) - truth_theta)
            row["theta_error"] = float(err.mean())
        if reference in scores and m != reference:
            diff = paired_difference(r, scores[reference])
            row[f"vs_{reference}"] = {"mean_diff": float(diff["mean_diff"]), "ci95": list(map(float, diff["ci95"]))}
        if validated and m not in ("truth", reference):
            row["warnings"] = _warning_rank(answers[m], r)
        out[m] = row
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--bundle", required=True, help="the bundle that answers (its scales and simulator score)")
    p.add_argument("--targets", nargs="+", required=True, help="NAME=STORE: a set of fresh simulations")
    p.add_argument("--all-data", nargs="*", default=[], help="every store of the bundle's simulator version")
    p.add_argument("--methods", nargs="+", default=None,
                   help="bundle methods (default: the bundle's default); with --answers-in: the files' methods to score")
    p.add_argument("--validate", action="store_true", help="re-simulate every answer (a GPU for the paper preset)")
    p.add_argument("--sim-option", nargs="*", default=[], help="KEY=VALUE simulator overrides (e.g. arch=cpu)")
    p.add_argument("--sim-batch", type=int, default=64, help="--validate's runs in flight")
    p.add_argument("--extract-workers", type=int, default=0,
                   help="--validate's feature-extraction processes (0: in the simulator's thread)")
    p.add_argument("--limit", type=int, default=None, help="first N targets of each set (a quick check)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--label", default="", help="with --answers-out: name methods LABEL:METHOD in the file")
    p.add_argument("--answers-out", default=None, help="also write every answer's parameters to this JSON file")
    p.add_argument("--answers-in", nargs="+", default=None, help="answers files to score instead of answering")
    p.add_argument("--no-truth", action="store_true", help="do not score (or re-simulate) the true parameters")
    p.add_argument("--per-target-out", default=None,
                   help="also write every target's answer, R_actual and R_surrogate per set and method (JSON)")
    p.add_argument("--out", required=True)
    return p


def _per_target(arrays: Any, answers: dict[str, list[Any]]) -> dict[str, Any]:
    """One set's targets and, per method, each answer (normalised), its R_actual (None unless validated or a
    stored row), R_surrogate and warnings: the rows a failure warning is fitted and checked on."""
    def r_actual(r: Any) -> float | None:
        return None if r.r_actual is None and r.r_known is None else _real_r(r)

    return {"keys": [str(k) for k in arrays.keys], "y": arrays.y.tolist(), "truth_theta": arrays.theta.tolist(),
            "methods": {m: {"theta": [r.theta.tolist() for r in res], "r_actual": [r_actual(r) for r in res],
                            "r_surrogate": [float(r.r_surrogate) for r in res],
                            "warnings": [list(r.warnings) for r in res]} for m, res in answers.items()}}


def _given(files: list[str] | None) -> dict[str, dict[str, Any]]:
    """{set: {label: {"theta", "warnings"}}} from answers files (labels must not repeat)."""
    out: dict[str, dict[str, Any]] = {}
    for f in files or []:
        data = json.loads(Path(f).read_text())
        if data.get("benchmark") != "user_targets_answers":
            raise SystemExit(f"error: {f} is not an answers file of this benchmark (--answers-out)")
        for name, s in data["sets"].items():
            for m, rec in s["methods"].items():
                if m in out.setdefault(name, {}):
                    raise SystemExit(f"error: method {m!r} of set {name!r} is in two answers files (use --label)")
                out[name][m] = rec
    return out


def _write(a: argparse.Namespace, result: dict[str, Any], saved: dict[str, Any], per_target: dict[str, Any]) -> None:
    """Write the result (and the answers / per-target files asked for) with the sets finished so far."""
    outs = [(a.out, json.dumps(result, indent=1))]
    if a.answers_out:
        outs.append((a.answers_out, json.dumps(saved)))
    if a.per_target_out:
        outs.append((a.per_target_out, json.dumps({"benchmark": "user_targets_per_target", "bundle": a.bundle,
                                                   "validated": a.validate, "sets": per_target})))
    for path, text in outs:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(text + "\n")


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)

    from invphys.inverter import load_inverter

    inv = load_inverter(a.bundle)
    given = _given(a.answers_in)
    if a.answers_in and a.methods:  # score only these of the files' methods
        given = {k: {m: r for m, r in v.items() if m in a.methods} for k, v in given.items()}
    methods = [] if a.answers_in else (a.methods or [inv.default_method])
    overrides = dict(kv.split("=", 1) for kv in a.sim_option)
    result: dict[str, Any] = {"benchmark": "user_targets", **_machine().provenance(),
                              "device": _device(), "bundle": a.bundle,
                              "bundle_id": inv.bundle.manifest.get("bundle_id"),
                              "simulator": inv.bundle.manifest["simulator"], "validated": a.validate,
                              "fail_below": FAIL_BELOW, "answers_in": a.answers_in, "sets": {}}
    saved: dict[str, Any] = {"benchmark": "user_targets_answers", "bundle": a.bundle, "seed": a.seed,
                             "bundle_id": inv.bundle.manifest.get("bundle_id"), "sets": {}}
    prefix = f"{a.label}:" if a.label else ""
    per_target: dict[str, Any] = {}
    for spec in a.targets:
        name, _, path = spec.partition("=")
        arrays = _store_rows(path)
        if a.limit:
            arrays.y, arrays.theta, arrays.keys = arrays.y[: a.limit], arrays.theta[: a.limit], arrays.keys[: a.limit]
        if a.answers_in and name not in given:
            raise SystemExit(f"error: the answers files hold no set {name!r}")
        if a.answers_in and a.limit:  # the files answer the whole store: their first N answers
            given[name] = {m: {"theta": r["theta"][: a.limit], "warnings": (r.get("warnings") or [])[: a.limit] or None}
                           for m, r in given[name].items()}
        print(f"{name}: {len(arrays.y)} targets from {path}", file=sys.stderr)
        timing: dict[str, float] = {}
        answers = _answers(inv, arrays, methods, a.all_data, a.seed, given.get(name), timing,
                           with_truth=not a.no_truth)
        saved["sets"][name] = {"store": path, "n_targets": len(arrays.y), "methods": {
            prefix + m: {"theta": [r.theta.tolist() for r in answers[m]], "warnings": [r.warnings for r in answers[m]],
                         "answer_ms_per_target": timing[m]} for m in methods}}
        t0, runs = time.perf_counter(), 0
        if a.validate:
            todo = _to_simulate(answers)
            inv.validate(todo, overrides=overrides, batch_size=a.sim_batch, extract_workers=a.extract_workers)
            runs = sum(len(r.candidates) for r in todo)
        validate_s = time.perf_counter() - t0
        rows = summarise(answers, a.validate, truth_theta=arrays.theta)
        per_target[name] = _per_target(arrays, answers)
        for m, ms in timing.items():
            rows[m]["answer_ms_per_target"] = ms
        result["sets"][name] = {"store": path, "n_targets": len(arrays.y), "validate_s": validate_s,
                                "validate_runs": runs, "validate_s_per_run": validate_s / runs if runs else None,
                                "sim_batch": a.sim_batch, "extract_workers": a.extract_workers, "methods": rows}
        _write(a, result, saved, per_target)  # after every set: a run cut short keeps the sets it finished
    for name, s in result["sets"].items():
        for m, row in s["methods"].items():
            print(f"{name:8s} {m:24s} R {row['r_mean']:.3f} [{row['r_ci95'][0]:.3f}, {row['r_ci95'][1]:.3f}] "
                  f"worst {row['r_worst']:.3f} theta error {row.get('theta_error', float('nan')):.4f}"
                  + _stored_text(row.get("stored_rows")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
