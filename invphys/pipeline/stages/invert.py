"""The ``invert`` stage: run every optimiser entry on the held-out targets and the named objectives.

1. Chooses ``targets.n`` held-out targets from the test partition (farthest-point sampling in
   standardised feature space, :mod:`invphys.core.target_selection`) and writes ``targets.json``.
2. For each ``optimizers`` entry builds its search space (``space: raw`` or a latent model's label)
   and evaluator (``evaluator: shared`` = decode then the shared surrogate, ``own_head`` = the latent
   model's own head). Goal-conditioned entries are trained once on the training partition's features
   (:meth:`Optimizer.prepare`) and cached in ``policies/<label>/``; a ``warm_start`` entry borrows the
   policy, space and evaluator of the ``gc_ppo`` entry it names with ``policy: <label>``.
3. Optimises each target (recovery reward R_gt, paper eq. 1) and/or each named objective, as the
   optimiser's ``problems`` attribute says, and writes ``results.json`` and ``results.csv``: one row per
   (optimiser, problem) with R_surr (the score on the optimiser's evaluator), evaluations, wall time,
   theta*, physical parameters and the predicted features.
4. Rewrites the run's inverter bundle ``OUT/inverter/`` with the trained policies and each entry's
   held-out scores (``invphys invert OUT/inverter ...`` then answers any target).
"""

from __future__ import annotations

import inspect
import logging
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.pipeline.artifacts import objectives, write_inverter
from invphys.pipeline.cache import BUNDLE_SECTIONS
from invphys.pipeline.stage_files import RESULTS_FILE, TARGETS_FILE, summarise

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("dataset", "surrogate", "latent_models", "optimizers", "objectives", "targets")
#: what the bundle alone reads: a change rewrites the cached stage's bundle (:func:`refresh`), no re-run
REFRESHED_BY: tuple[str, ...] = BUNDLE_SECTIONS


def refresh(ctx: StageContext) -> bool:
    """Rewrite the run's bundle from the finished stage's policies (the spec's pools, default or
    description changed): seconds, where re-running the stage would refit every policy."""
    write_inverter(ctx, with_policies=True)
    return True


def select(ctx: StageContext) -> dict[str, Any]:
    """The held-out targets: dataset rows, features, true theta and physical parameters.

    With ``targets.values`` or ``targets.file`` these are the user's own targets instead: no dataset
    rows and no ground truth (``rows`` are None, ``theta`` and ``params`` are None).
    """
    from invphys.core.target_selection import select_targets

    data = ctx.dataset()
    spec_t = ctx.spec.targets
    if spec_t.values is not None or spec_t.file is not None:
        from invphys.core.user_targets import from_mappings, read_target_file, require_exact

        if spec_t.file is not None:
            user = require_exact(read_target_file(spec_t.file, data.feature_names), "targets.file")
        else:
            user = require_exact(from_mappings(spec_t.values, data.feature_names, source="targets.values"),
                                 "targets.values")
        return {"rows": [None] * len(user), "features": user.values.tolist(), "theta": None, "params": None,
                "ground_truth": False, "labels": user.labels, "feature_names": list(data.feature_names),
                "param_names": list(data.param_names), "scales": ctx.scales().tolist(),
                "selection": "file" if spec_t.file is not None else "values", "validate": spec_t.validate_n}
    _, test_idx = ctx.split()
    # farthest-point sampling standardises by dataset.path's rows alone: extra_train rows never move the targets
    rows = select_targets(data.y[:ctx.primary_rows()], test_idx, ctx.spec.targets.n, ctx.spec.targets.selection,
                          ctx.seed)
    return {"rows": rows.tolist(), "features": data.y[rows].tolist(), "theta": data.theta[rows].tolist(),
            "params": data.params[rows].tolist(), "feature_names": list(data.feature_names),
            "param_names": list(data.param_names), "scales": ctx.scales().tolist(),
            "selection": ctx.spec.targets.selection, "validate": ctx.spec.targets.validate_n}


class _Entries:
    """Builds each optimiser entry's plugin, space and predictor once (goal-conditioned ones trained)."""

    def __init__(self, ctx: StageContext, train_targets: np.ndarray, scales: np.ndarray) -> None:
        from invphys.core.spec import optimizer_plugin_block

        self.ctx = ctx
        self.train_targets = train_targets
        self.scales = scales
        self.blocks = {k: dict(v) for k, v in ctx.spec.optimizers.items()}
        self.plugins = {k: ctx.registry.create("optimizer", optimizer_plugin_block(b)) for k, b in self.blocks.items()}
        self._built: dict[str, tuple[Any, Any, Any, str]] = {}
        self.prepare_metrics: dict[str, Any] = {}
        for label, plugin in self.plugins.items():  # fail early on a bad policy label
            if plugin.name == "warm_start" and plugin.config.policy_path is None:
                self._policy_label(label)

    def space(self, label: str) -> tuple[Any, Any, Any, str]:
        """(space, predict, latent, evaluator) of an entry (a warm start uses its policy's)."""
        from invphys.core.spaces import latent_space, make_predict, raw_space

        if label in self._built:
            return self._built[label]
        plugin = self.plugins[label]
        if plugin.name == "warm_start":
            built = self.space(self._policy_label(label))
        else:
            block = self.blocks[label]
            space_label, evaluator = block.get("space", "raw"), block.get("evaluator", "shared")
            d = self.ctx.dataset().theta.shape[1]
            latent = None if space_label == "raw" else self.ctx.latent(space_label)
            space = raw_space(d) if latent is None else latent_space(latent, name=space_label)
            predict = make_predict(space, self.ctx.surrogate(), latent, evaluator)
            built = (space, predict, latent, evaluator)
        self._built[label] = built
        return built

    def _policy_label(self, label: str) -> str:
        plugin = self.plugins[label]
        policy = getattr(plugin.config, "policy", None)
        if policy is None:
            if getattr(plugin.config, "policy_path", None):
                raise InvphysError(f"optimizers.{label}: in a spec, name the gc_ppo entry with `policy: <label>`")
            raise InvphysError(f"optimizers.{label}: warm_start needs `policy: <label of a gc_ppo entry>`")
        if policy not in self.plugins or not getattr(self.plugins[policy], "goal_conditioned", False):
            gc = [k for k, p in self.plugins.items() if getattr(p, "goal_conditioned", False)]
            raise InvphysError(f"optimizers.{label}.policy: {policy!r} is not a goal-conditioned entry "
                               f"(goal-conditioned entries: {', '.join(gc) or 'none'})")
        return policy

    def plugin(self, label: str) -> Any:
        """The ready-to-use optimiser: trained (goal-conditioned) or attached (warm start)."""
        plugin = self.plugins[label]
        if getattr(plugin, "goal_conditioned", False) and not getattr(plugin, "prepared", True):
            self._prepare(label)
            plugin = self.plugins[label]  # the cached policy may have replaced it
        if plugin.name == "warm_start" and plugin.policy is None:
            plugin.attach(self.plugin(self._policy_label(label)))
        return plugin

    def _prepare(self, label: str) -> None:
        from invphys.plugins.baselines import learns_from_rows

        plugin = self.plugins[label]
        cache = self.ctx.stage_dir / "policies" / label
        if learns_from_rows(plugin):  # a dataset baseline (npe, ...): fitted on the training rows, kept for the bundle
            data, (train_idx, _) = self.ctx.dataset(), self.ctx.split()
            self.ctx.log(f"{label}: fitting {plugin.name} on {len(train_idx)} training rows")
            self.prepare_metrics[label] = plugin.fit(data.theta[train_idx], data.y[train_idx], self.scales,
                                                     progress=self.ctx.progress)
            if hasattr(plugin, "save"):
                plugin.save(cache)
            return
        space, predict, _, _ = self.space(label)
        if getattr(plugin.config, "seed", 0) is None:
            plugin.config.seed = self.ctx.seed
        lam = penalty_of(self.blocks[label])
        extra: dict[str, Any] = {}
        if lam:
            from invphys.evaluators.uncertainty import UncertaintyPenalty

            if "penalty" not in inspect.signature(plugin.prepare).parameters:
                raise InvphysError(f"optimizers.{label}.uncertainty_penalty: {plugin.name} cannot train with a penalty")
            pen = UncertaintyPenalty(self.ctx.surrogate(), self.scales, lam)
            predict = pen.predict_points(lambda p: space.to_theta(space.clip(p)))
            extra["penalty"] = pen.penalty
        if hasattr(plugin, "load") and (cache / "gc_ppo.json").is_file() and hasattr(plugin, "save"):
            from invphys.models.base import LegacyPickleError

            try:
                loaded = type(plugin).load(cache)
            except LegacyPickleError:  # a run made before pickle-free saves: train again, never unpickle
                self.ctx.log(f"{label}: the cached policy is in the older pickled format; training it again")
                loaded = None
            if loaded is not None and loaded.config == plugin.config and loaded.meta.get("space", {}).get("name") == space.name \
                    and float(loaded.meta.get("uncertainty_penalty", 0.0)) == lam:
                self.plugins[label] = loaded
                self.prepare_metrics[label] = {**loaded.metrics, "cached": True}
                self.ctx.log(f"{label}: loaded the cached policy from {cache}")
                return
        self.ctx.log(f"{label}: training {plugin.name} on {len(self.train_targets)} training targets"
                     + (f" (uncertainty penalty {lam:g})" if lam else ""))
        if "tracker" in inspect.signature(plugin.prepare).parameters:
            extra["tracker"] = self.ctx.tracker.scoped(f"invert/policy/{label}")
        metrics = plugin.prepare(space, predict, self.train_targets, self.scales, progress=self.ctx.progress,
                                 **extra)
        if lam and isinstance(getattr(plugin, "meta", None), dict):
            plugin.meta["uncertainty_penalty"] = lam
        if hasattr(plugin, "save"):
            plugin.save(cache)
        self.prepare_metrics[label] = metrics


def problem_seed(seed: int, label: str, problem_id: str, target: np.ndarray | None) -> int:
    """An entry's seed for one problem: for a target, the stream ``invphys invert`` gives the method's first
    search of that target (:func:`~invphys.inverter.seeds.target_seed`, ``search:0``), so the bundle answers
    as this stage did; for a named objective, its name. Never the problem's position among the others."""
    from invphys.inverter.seeds import target_seed

    if target is None:
        return target_seed(seed, label, np.zeros(0), np.zeros(0, dtype=bool), f"objective:{problem_id}")
    return target_seed(seed, label, target, np.ones(len(target), dtype=bool), "search:0")


def penalty_of(block: dict[str, Any]) -> float:
    """An optimiser entry's ``uncertainty_penalty`` lambda (0: none)."""
    return float(block.get("uncertainty_penalty", 0.0) or 0.0)


def _problems_of(plugin: Any, has_objectives: bool) -> tuple[bool, bool]:
    kind = getattr(plugin, "problems", "both")
    if plugin.goal_conditioned:
        return True, False
    if kind == "objectives" and not has_objectives:
        return True, False
    return kind in ("both", "targets"), kind in ("both", "objectives") and has_objectives


def run(ctx: StageContext) -> dict[str, Any]:
    from invphys.core.atomic import write_json
    from invphys.core.objectives import RecoveryObjective, feature_standardiser
    from invphys.core.spaces import build_problem

    data = ctx.dataset()
    train_idx, _ = ctx.split()
    scales = ctx.scales()
    flat = [n for n, s in zip(data.feature_names, scales, strict=True) if s <= 1e-10]
    if flat:
        ctx.log(f"feature(s) {', '.join(flat)} have no spread in the training data "
                f"(p95 - p5 = 0): any predicted deviation there drives R_gt to 0", logging.WARNING)
    targets = select(ctx)
    write_json(ctx.stage_dir / TARGETS_FILE, targets)
    named = objectives(ctx)
    y_train = data.y[train_idx]
    mean, std = feature_standardiser(y_train)
    surrogate = ctx.surrogate()
    entries = _Entries(ctx, y_train, scales)
    param_names = data.param_names
    rows: list[dict[str, Any]] = []
    ctx.log(f"{len(targets['rows'])} targets, {len(named)} objectives, {len(entries.plugins)} optimisers")
    for label in entries.plugins:
        plugin = entries.plugin(label)
        space, predict, latent, evaluator = entries.space(label)
        budget = int(getattr(plugin, "evaluation_budget", 0) or getattr(plugin.config, "budget", 0) or 5000)
        on_targets, on_objectives = _problems_of(plugin, bool(named))
        problems: list[tuple[str, str, Any, np.ndarray | None, int | None]] = []
        if on_targets:
            for j, y_t in enumerate(np.asarray(targets["features"])):
                problems.append(("target", f"t{j:02d}", RecoveryObjective(y_t, scales), y_t, j))
        if on_objectives:
            problems += [("objective", name, obj, None, None) for name, obj in named.items()]
        t_entry = time.perf_counter()
        for kind, problem_id, objective, y_star, k in problems:
            problem = build_problem(space, objective, budget, surrogate=surrogate, latent=latent,
                                    evaluator=evaluator, predict=predict, target=y_star,
                                    seed=problem_seed(ctx.seed, label, problem_id, y_star),
                                    feature_mean=mean, feature_std=std)
            lam = penalty_of(entries.blocks[label])
            if lam:  # score = R - lambda * normalised ensemble std (the row keeps the plain R_surr)
                from invphys.evaluators.uncertainty import penalised_problem

                problem = penalised_problem(problem, surrogate, scales, lam)
            problem.info["tracker"] = ctx.tracker.scoped(f"invert/{label}/{problem_id}")
            res = plugin.optimize(problem)
            counted = problem.info["counter"].count
            predicted = res.info.get("predicted")
            if predicted is None:
                predicted = np.asarray(surrogate.predict(np.asarray(res.theta)[None, :]))[0].tolist()
            theta = np.clip(np.asarray(res.theta, dtype=np.float64), 0.0, 1.0)
            rows.append({
                "optimizer": label, "type": plugin.name, "space": space.name, "evaluator": evaluator,
                "problem": kind, "problem_id": problem_id, "target_index": k,
                "dataset_row": None if k is None else targets["rows"][k],
                "r_surrogate": float(res.score) if not lam else float(np.asarray(
                    objective(np.asarray(predicted, dtype=np.float64)[None, :])).reshape(-1)[0]),
                **({"uncertainty_penalty": lam, "in_loop_score": float(res.score)} if lam else {}),
                "evaluations": int(res.evaluations),
                "counted_evaluations": int(counted), "wall_time_s": float(res.wall_time_s),
                "theta": theta.tolist(), "point": np.asarray(res.point).tolist(),
                "params": dict(zip(param_names, _physical(ctx, theta), strict=True)),
                "predicted": list(map(float, predicted)),
                "history": [[int(e), float(s)] for e, s in res.history],
            })
        if problems:
            mine = [r for r in rows if r["optimizer"] == label]
            ctx.log(f"{label}: {len(problems)} problems, mean R_surr "
                    f"{np.mean([r['r_surrogate'] for r in mine]):.3f} in {time.perf_counter() - t_entry:.1f} s")
    write_json(ctx.stage_dir / RESULTS_FILE, rows)
    _write_csv(ctx.stage_dir / "results.csv", rows)
    return {"targets": len(targets["rows"]), "objectives": sorted(named), "rows": len(rows),
            "prepare": entries.prepare_metrics, "optimizers": summarise(rows),
            "inverter": write_inverter(ctx, with_policies=True)}


def _physical(ctx: StageContext, theta: np.ndarray) -> list[float]:
    try:
        return ctx.simulator().parameter_space().denormalize(theta).tolist()
    except Exception:
        return [float("nan")] * len(theta)


def _write_csv(path: Any, rows: list[dict[str, Any]]) -> None:
    import pandas as pd

    flat = [{k: v for k, v in r.items() if k not in ("history", "predicted", "point", "params", "theta")}
            | {f"theta_{i}": t for i, t in enumerate(r["theta"])} | {f"param_{k}": v for k, v in r["params"].items()}
            for r in rows]
    pd.DataFrame(flat).to_csv(path, index=False)


