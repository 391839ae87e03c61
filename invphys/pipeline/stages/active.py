"""The ``active`` stage: active learning rounds on the targets (spec section ``active:``).

Round r (0 .. ``rounds``) for the first ``active.targets`` targets (default: the validated ones):

1. propose: CMA-ES (ask/tell, ``budget`` surrogate evaluations per target, optionally penalised by
   the ensemble's std) on the current surrogate, started at each target's best simulated answer so
   far (round 0: the ``start`` label's answer, e.g. the nearest-neighbour baseline); ``proposals``
   independent searches per target (seeds differ) give that many proposals;
2. simulate every proposal in one batch through the validator: round r's R_actual is the best of a
   target's proposals, and the best simulated answer per target so far is the ``active_learning``
   method's answer after round r (with ``keep_start``, the start's validated R_actual counts too);
3. add the successfully simulated proposals to the training rows and retrain the surrogate (same
   plugin and config as the train stage; ``max_epochs`` caps it). The dataset store is not modified:
   the added rows are written to ``added.npz``.

Resumable: every finished round's state (answers, simulated rows, round records) goes atomically to
``progress.npz``, keyed by every ``active`` setting but ``rounds``; a stopped stage (time limit, kill)
resumes after its last finished round, and raising ``active.rounds`` later adds rounds to the
recorded ones instead of starting over (other settings start afresh).

Writes ``rounds.json`` (per round: training rows, the surrogate's R^2 on the test partition, mean
R_actual of the proposals and of the best-so-far answers with bootstrap intervals, simulator runs
and time), ``rows.json``/``validation.json`` (the final answers as report rows: label
``active_learning``) and ``surrogate_round<r>/`` (each retrained surrogate). The report shows the
rounds and treats ``active_learning`` like any method. Policies are not retrained.

``active.polish`` (off by default): after the last round, CMA-ES on the real simulator from each
target's best answer whose R_actual is below ``polish.below`` (``budget`` new runs per target, each
generation of all polished targets one batch; the answer is the best simulated point, its start
included), reported as a second label ``active_polished`` whose cost adds the polish's runs and GPU
seconds to ``active_learning``'s. Every simulated batch is logged to ``polish.npz``; a re-run replays
it (a stopped polish resumes after its last batch; a larger budget extends a smaller one). Its
settings are not part of the rounds' checkpoint key, so adding a polish never re-runs the rounds.
A list of polish settings runs passes, each from the previous pass's answers (its own log,
``polish_pass<k>.npz``), e.g. a first pass on the worst targets and a second, wider one after it.
A pass's ``confirm: K`` (off by default) re-simulates each target's best ``confirm_candidates``
points K times after its search (same log) and answers with the best mean R, which the report rows
then carry as R_actual (the search's answer is a best-of-N run of a slightly chaotic simulator).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.pipeline.stage_files import (
    ROUNDS_FILE,
    baselines,
    load_evaluation_rows,
    load_results,
    load_validation,
)

if TYPE_CHECKING:
    from invphys.pipeline.context import StageContext

DEPENDS_ON: tuple[str, ...] = ("simulator", "features", "validator", "surrogate", "targets", "evaluation", "active")

LABEL = "active_learning"


def _start_r_actual(ctx: StageContext, label: str, ks: list[int], m: int) -> tuple[np.ndarray, np.ndarray, float]:
    """The start answers' validated R_actual per target (-inf where not validated), their simulated
    features (NaN there) and their mean simulator runs per target (what the start already cost)."""
    rows = [r for r in [*(load_validation(ctx) or []), *load_evaluation_rows(ctx)]
            if r.get("optimizer") == label and r.get("problem") == "target" and r.get("r_actual") is not None]
    by = {r["target_index"]: r for r in rows}
    r_act = np.array([float(by[k]["r_actual"]) if k in by and np.isfinite(by[k]["r_actual"]) else -np.inf
                      for k in ks])
    actual = np.array([by[k]["actual"] if k in by and by[k].get("actual") else [np.nan] * m for k in ks],
                      dtype=np.float64)
    runs = float(np.mean([by[k].get("simulator_runs") or 1 for k in ks if k in by])) if by else 0.0
    return r_act, actual, runs


def _starts(ctx: StageContext, label: str, ks: list[int], targets: dict[str, Any]) -> np.ndarray:
    rows, _ = load_results(ctx)
    pool = rows + load_evaluation_rows(ctx)
    if not any(r["optimizer"] == label for r in pool) and label in ctx.spec.evaluation.baselines:
        pool += baselines(ctx, targets)[0]
    by = {r["target_index"]: r["theta"] for r in pool if r["optimizer"] == label and r["problem"] == "target"}
    missing = [k for k in ks if k not in by]
    if missing:
        labels = sorted({r["optimizer"] for r in pool})
        raise InvphysError(f"active.start: {label!r} answered no target {missing[:5]} (labels with answers: "
                           f"{', '.join(labels) or 'none'})")
    return np.array([by[k] for k in ks], dtype=np.float64)


def _retrain(ctx: StageContext, theta: np.ndarray, y: np.ndarray) -> Any:
    block = dict(ctx.spec.surrogate or {})
    kind = block.pop("type")
    if ctx.spec.active is not None and ctx.spec.active.max_epochs:
        block["max_epochs"] = ctx.spec.active.max_epochs
    cls = ctx.registry.get("surrogate", kind)
    model = cls(cls.Config(**block))
    model.fit(theta, y)
    return model


@dataclass
class _Inputs:
    """What every round works on: the targets (``ks`` of ``targets``, their features and scales), the
    training and test rows, the simulator the proposals run on, and what the start answers cost."""

    targets: dict[str, Any]
    ks: list[int]
    feats: np.ndarray
    scales: np.ndarray
    data: Any
    theta_tr: np.ndarray
    y_tr: np.ndarray
    test_idx: np.ndarray
    sim: Any
    start_r: np.ndarray
    start_runs: float

    @property
    def n(self) -> int:
        return len(self.ks)


@dataclass
class _State:
    """The rounds so far: each target's best simulated answer, the rows every round added, the round
    records, the surrogate the next round proposes with, and the checkpoint key."""

    best_theta: np.ndarray
    best_r: np.ndarray
    best_y: np.ndarray
    added_theta: list[np.ndarray]
    added_y: list[np.ndarray]
    rounds: list[dict[str, Any]]
    surrogate: Any
    key: str
    first: int = 0

    @property
    def best(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.best_theta, self.best_r, self.best_y


def run(ctx: StageContext) -> dict[str, Any]:
    """Run (or resume) the active-learning rounds, then the optional polish; see the module docstring."""
    sec = ctx.spec.active
    if sec is None:
        raise InvphysError("the active stage needs an 'active' section")
    inp, best = _inputs(ctx, sec)
    st = _resume(ctx, sec, inp, best)
    for r in range(st.first, sec.rounds + 1):
        _one_round(ctx, sec, r, inp, st)
        _save_checkpoint(ctx, st.key, st.rounds, st.best, st.added_theta, st.added_y)
        if r == sec.rounds:
            break
        st.surrogate = _retrain_round(ctx, r + 1, inp.theta_tr, inp.y_tr, st.added_theta, st.added_y, st.rounds)
        _save_checkpoint(ctx, st.key, st.rounds, st.best, st.added_theta, st.added_y)
    return _finish(ctx, sec, inp, st)


def _inputs(ctx: StageContext, sec: Any) -> tuple[_Inputs, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The rounds' inputs, and the start answers (theta, validated R_actual, features) they improve on."""
    from invphys.evaluators.simulator_loop import SimulatorEvaluator

    _, targets = load_results(ctx)
    n = min(sec.targets or int(ctx.spec.targets.validate_n) or len(targets["rows"]), len(targets["rows"]))
    ks = list(range(n))
    feats = np.asarray(targets["features"], dtype=np.float64)[ks]
    scales = np.asarray(targets["scales"], dtype=np.float64)
    data = ctx.dataset()
    train_idx, test_idx = ctx.split()
    validator = ctx.registry.create("validator", ctx.spec.validator)
    if not hasattr(validator, "simulate_features"):
        raise InvphysError("the active stage simulates through a validator with simulate_features ('simulator')")
    sim = SimulatorEvaluator.from_validator(validator, ctx.simulator(), ctx.extractor())
    best_theta = _starts(ctx, sec.start, ks, targets)
    best_r, best_y, start_runs = np.full(n, -np.inf), np.full_like(feats, np.nan), 0.0
    if sec.keep_start:
        best_r, best_y, start_runs = _start_r_actual(ctx, sec.start, ks, feats.shape[1])
        if not np.isfinite(best_r).any():
            raise InvphysError(f"active.keep_start: the validate stage validated no {sec.start!r} answer")
    inp = _Inputs(targets=targets, ks=ks, feats=feats, scales=scales, data=data, theta_tr=data.theta[train_idx],
                  y_tr=data.y[train_idx], test_idx=test_idx, sim=sim, start_r=best_r.copy(), start_runs=start_runs)
    return inp, (best_theta, best_r, best_y)


def _resume(ctx: StageContext, sec: Any, inp: _Inputs, best: tuple[np.ndarray, np.ndarray, np.ndarray]) -> _State:
    """Round 0's state, or the saved rounds' when ``progress.npz`` matches (also when ``rounds`` grew),
    with the surrogate the next round proposes with."""
    surrogate = ctx.surrogate()
    key = _checkpoint_key(ctx, inp.n, inp.feats)
    st = _State(*best, added_theta=[], added_y=[], rounds=[], surrogate=surrogate, key=key)
    saved = _load_checkpoint(ctx, (key, _checkpoint_key(ctx, inp.n, inp.feats, legacy=True)))
    if saved is None:
        return st
    st = _State(best_theta=saved["best_theta"], best_r=saved["best_r"], best_y=saved["best_y"],
                added_theta=saved["added_theta"], added_y=saved["added_y"], rounds=saved["rounds"],
                surrogate=surrogate, key=saved["key"],  # a legacy key stays in use: the polish logs are keyed by it
                first=len(saved["rounds"]))
    ctx.log(f"resuming after round {st.first - 1} ({st.first} rounds recorded in {CHECKPOINT_FILE})")
    if st.first <= sec.rounds:
        st.surrogate = _surrogate_for(ctx, st.first, inp.theta_tr, inp.y_tr, st.added_theta, st.added_y, st.rounds,
                                      st.key, st.best)
    elif st.first > 1:  # more rounds recorded than asked for: they are all kept
        st.surrogate = _surrogate_for(ctx, st.first - 1, inp.theta_tr, inp.y_tr, st.added_theta[:-1],
                                      st.added_y[:-1], st.rounds[:-1], st.key, None)
    return st


def _one_round(ctx: StageContext, sec: Any, r: int, inp: _Inputs, st: _State) -> None:
    """Round ``r``: propose on the surrogate, simulate every proposal, keep each target's best answer,
    record the round and the rows it adds."""
    from invphys.core.objectives import recovery_reward
    from invphys.evaluation.stats import bootstrap_mean_ci
    from invphys.evaluators.simulator_loop import refine_targets
    from invphys.evaluators.uncertainty import UncertaintyPenalty
    from invphys.models.data import r2_scores

    n, feats, scales, sim, data, test_idx = inp.n, inp.feats, inp.scales, inp.sim, inp.data, inp.test_idx
    t0 = time.perf_counter()
    pen = UncertaintyPenalty(st.surrogate, scales, sec.uncertainty_penalty)
    k_prop = sec.proposals
    refined = refine_targets(np.repeat(feats, k_prop, axis=0), np.repeat(st.best_theta, k_prop, axis=0), scales,
                             pen.predict, sec.budget, sec.popsize, sec.sigma0, seed=ctx.seed * 1000 + r,
                             score=lambda y, t, pen=pen: recovery_reward(y, t, scales) - pen.penalty(y))
    proposals = np.array([x.theta for x in refined])  # target i's proposals: rows i*k .. i*k+k-1
    propose_s = time.perf_counter() - t0
    runs0, sim_s0 = sim.runs, sim.wall_time_s
    y_sim = sim(proposals)
    ok = np.all(np.isfinite(y_sim), axis=1)
    r_all = np.where(ok, recovery_reward(np.where(ok[:, None], y_sim, 0.0), np.repeat(feats, k_prop, axis=0),
                                         scales), 0.0).reshape(n, k_prop)
    pick = np.arange(n) * k_prop + r_all.argmax(axis=1)
    r_act = r_all.max(axis=1)
    better = r_act > st.best_r
    st.best_r = np.where(better, r_act, st.best_r)
    st.best_theta = np.where(better[:, None], proposals[pick], st.best_theta)
    st.best_y = np.where(better[:, None], y_sim[pick], st.best_y)
    r2 = (float(r2_scores(data.y[test_idx], st.surrogate.predict(data.theta[test_idx]))[0])
          if len(test_idx) > 1 else None)
    ev = ctx.spec.evaluation
    m, lo, hi = bootstrap_mean_ci(r_act, ev.bootstrap, ev.confidence, ctx.seed)
    bm, blo, bhi = bootstrap_mean_ci(st.best_r, ev.bootstrap, ev.confidence, ctx.seed)
    st.rounds.append({"round": r, "train_rows": int(len(inp.theta_tr) + sum(len(a) for a in st.added_theta)),
                      "surrogate_r2_test": r2, "r_actual_mean": m, "r_actual_ci95": [lo, hi],
                      "best_so_far_mean": bm, "best_so_far_ci95": [blo, bhi], "failed": int((~ok).sum()),
                      "simulator_runs": sim.runs - runs0, "simulator_s": sim.wall_time_s - sim_s0,
                      "propose_s": propose_s, "device": sim.device})
    ctx.log(f"round {r}: {st.rounds[-1]['train_rows']} training rows, surrogate R^2 {r2 if r2 is None else round(r2, 3)}, "
            f"R_actual {m:.3f} [{lo:.3f}, {hi:.3f}], best so far {bm:.3f}")
    st.added_theta.append(proposals[ok])
    st.added_y.append(y_sim[ok])


def _finish(ctx: StageContext, sec: Any, inp: _Inputs, st: _State) -> dict[str, Any]:
    """Write ``rounds.json``, ``added.npz``, the answers' report and validation rows (and the polish's);
    return the stage's summary."""
    from invphys.core.atomic import write_json
    from invphys.pipeline.artifacts import to_params

    n, rounds, sim = inp.n, st.rounds, inp.sim
    write_json(ctx.stage_dir / ROUNDS_FILE, rounds)
    trained_on = len(rounds) - 1  # the last round's runs are simulated but not yet trained on
    if trained_on:
        np.savez_compressed(ctx.stage_dir / "added.npz", theta=np.concatenate(st.added_theta[:trained_on]),
                            y=np.concatenate(st.added_y[:trained_on]))
    physical = to_params(ctx)
    runs_per_target = sum(x["simulator_runs"] for x in rounds) / max(n, 1) + inp.start_runs
    wall = float(sum(x["propose_s"] + x["simulator_s"] + x.get("retrain_s", 0.0) for x in rounds) / n)
    row_inputs = {"to_params": physical, "surrogate": st.surrogate, "feats": inp.feats, "scales": inp.scales,
                "ks": inp.ks, "targets": inp.targets, "evaluations": int(sec.budget * sec.proposals * (sec.rounds + 1)),
                "device": sim.device or next((x["device"] for x in reversed(rounds) if x.get("device")), "cpu")}
    rows, val = _answer_rows(row_inputs, LABEL, "active_learning", "shared", st.best_theta, st.best_r, st.best_y,
                             np.full(n, runs_per_target), np.full(n, wall))
    polish_summary = None
    if sec.polish is not None:
        pol, share, polish_summary = _polish_passes(ctx, sec.polish, st.key, len(rounds), inp.feats, inp.scales,
                                                    st.best, sim, runs_per_target, wall)
        prow, pval = _answer_rows({**row_inputs, "device": pol.device or row_inputs["device"]}, POLISH_LABEL,
                                  "active_learning+simulator", "simulator", pol.theta, pol.r_actual, pol.features,
                                  runs_per_target + pol.runs, wall + share)
        rows, val = rows + prow, val + pval
        write_json(ctx.stage_dir / POLISH_FILE, polish_summary)
    write_json(ctx.stage_dir / "rows.json", rows)
    write_json(ctx.stage_dir / "validation.json", val)
    start_r = inp.start_r
    return {"targets": n, "rounds": rounds, "simulator_runs": sum(x["simulator_runs"] for x in rounds),
            "resumed_after_round": st.first - 1 if st.first else None, "proposals": sec.proposals,
            "start": sec.start, "start_simulator_runs_per_target": inp.start_runs,
            "start_r_actual_mean": float(np.mean(start_r[np.isfinite(start_r)])) if sec.keep_start else None,
            **({"polish": polish_summary} if polish_summary is not None else {})}


def _answer_rows(c: dict[str, Any], label: str, kind: str, evaluator: str, theta: np.ndarray, r_act: np.ndarray,
                 actual: np.ndarray, runs: np.ndarray, wall: np.ndarray) -> tuple[list[dict], list[dict]]:
    """Report rows and validation rows of one label's answers (per-target runs and wall time)."""
    from invphys.core.objectives import recovery_reward

    predicted = c["surrogate"].predict(theta)
    rows, val = [], []
    for i, k in enumerate(c["ks"]):
        row = {"optimizer": label, "type": kind, "role": "method", "space": "raw", "evaluator": evaluator,
               "problem": "target", "problem_id": f"t{k:02d}", "target_index": k,
               "dataset_row": c["targets"]["rows"][k],
               "r_surrogate": float(recovery_reward(predicted[i], c["feats"][i], c["scales"])),
               "evaluations": c["evaluations"], "counted_evaluations": c["evaluations"],
               "wall_time_s": float(wall[i]), "theta": theta[i].tolist(), "point": theta[i].tolist(),
               "params": dict(zip(c["targets"]["param_names"], c["to_params"](theta[i]), strict=True)),
               "predicted": predicted[i].tolist(), "history": [], "simulator_runs": float(runs[i]),
               "device": c["device"]}
        rows.append(row)
        finite = bool(np.isfinite(r_act[i]) and r_act[i] > -np.inf)
        ok = bool(np.all(np.isfinite(actual[i])))
        val.append({**{key: row[key] for key in ("optimizer", "type", "role", "space", "evaluator", "problem",
                                                  "problem_id", "target_index", "dataset_row", "evaluations",
                                                  "wall_time_s", "theta", "simulator_runs", "device")},
                    "r_surrogate": row["r_surrogate"], "r_actual": float(r_act[i]) if finite else float("nan"),
                    "gap": row["r_surrogate"] - float(r_act[i]) if finite else float("nan"),
                    "failure": None if ok else "no proposal simulated successfully",
                    "actual": actual[i].tolist() if ok else None, "sim_time_s": None})
    return rows, val


POLISH_LABEL = "active_polished"
POLISH_FILE = "polish.json"
POLISH_LOG = "polish.npz"


def _polish_passes(ctx: StageContext, cfg: Any, key: str, n_rounds: int, feats: np.ndarray, scales: np.ndarray,
                   start: tuple[np.ndarray, np.ndarray, np.ndarray], sim: Any, runs_per_target: float,
                   wall: float) -> tuple[Any, np.ndarray, dict[str, Any]]:
    """Run ``active.polish`` (one pass, or a list of passes each from the previous pass's answers).

    Returns the final answers with the runs of all passes, each target's share of the polish's GPU
    seconds, and ``polish.json``'s content (a list adds ``passes``: every pass's own summary).
    """
    from dataclasses import replace

    from invphys.inverter.settings import PolishSettings

    passes = cfg if isinstance(cfg, list) else [cfg]
    for p in passes:  # the inverter's one model of polish settings checks every pass before any simulation
        PolishSettings.checked(names={f: f"active.polish.{f}" for f in PolishSettings.model_fields}, **p.model_dump())
    current, total, share, summaries = start, None, np.zeros(len(feats)), []
    for k, settings in enumerate(passes):
        pol = _polish(ctx, settings, key, n_rounds, feats, scales, *current, sim, k, passes[:k])
        pass_share = pol.runs / max(int(pol.runs.sum()), 1) * pol.seconds  # a target's share of the GPU time
        summaries.append(_polish_summary(ctx, settings, pol, current[1], runs_per_target + (
            total.runs if total is not None else 0), wall + share, pass_share))
        share = share + pass_share
        total = pol if total is None else replace(
            pol, runs=total.runs + pol.runs, polished=total.polished | pol.polished, seconds=total.seconds + pol.seconds,
            batches=total.batches + pol.batches, replayed_runs=total.replayed_runs + pol.replayed_runs,
            device=pol.device or total.device)
        current = (pol.theta, pol.r_actual, pol.features)
    if not isinstance(cfg, list):
        return total, share, summaries[0]
    summary = _polish_summary(ctx, passes[-1], total, start[1], runs_per_target, wall, share)
    summary["settings"] = [p.key_dump() for p in passes]
    return total, share, {**summary, "passes": summaries}


def _polish(ctx: StageContext, cfg: Any, key: str, n_rounds: int, feats: np.ndarray, scales: np.ndarray,
            theta: np.ndarray, r_act: np.ndarray, actual: np.ndarray, sim: Any, index: int = 0,
            previous: list[Any] | None = None) -> Any:
    """One polish pass: CMA-ES on the simulator from the answers below ``cfg.below``; every simulated
    batch is logged to ``polish.npz`` (pass ``k`` > 0: ``polish_pass<k+1>.npz``), and a re-run replays
    it (nothing finished is simulated twice)."""
    from invphys.evaluators.polish import BatchLog, confirm, polish
    from invphys.pipeline.cache import digest

    fields = {"rounds": key, "n_rounds": n_rounds, "popsize": cfg.popsize, "sigma0": cfg.sigma0, "below": cfg.below}
    if index:  # a later pass depends on every earlier pass's settings (its starts are their answers)
        fields["after"] = [p.key_dump() for p in previous or []]
    log_key = digest(fields)  # not the budget: a larger budget replays the smaller one's batches
    log_name = POLISH_LOG if index == 0 else f"polish_pass{index + 1}.npz"
    batches = BatchLog(ctx.stage_dir / log_name, log_key, sim, log=ctx.log,
                       chunk=int((ctx.spec.validator or {}).get("batch_size") or 0) or None,
                       replace_other=True)  # the stage's own folder: a log of other settings starts afresh
    t0 = time.perf_counter()
    pol = polish(feats, theta, r_act, actual, scales, batches, cfg.budget, cfg.popsize, cfg.sigma0, cfg.below,
                 seed=ctx.seed * 1000 + 999 + 7919 * index)
    if cfg.confirm:  # through the same log, after the search's batches (a log made without it still replays)
        selected = pol.r_actual
        conf = confirm(pol, feats, scales, batches, cfg.confirm, cfg.confirm_candidates)
        pol = conf.apply(pol)
        ctx.log(f"polish pass {index + 1}: confirmed {cfg.confirm_candidates} candidates x {cfg.confirm} re-runs; "
                f"mean R_actual {float(np.mean(selected)):.3f} (best of N) -> {float(np.mean(pol.r_actual)):.3f} "
                f"(mean of re-runs), {int(conf.changed.sum())} answers changed")
    ctx.log(f"polish pass {index + 1}: {int(pol.polished.sum())} targets below {cfg.below}, "
            f"{int(pol.runs.sum())} simulator runs "
            f"({pol.replayed_runs} replayed) in {time.perf_counter() - t0:.1f} s; mean R_actual "
            f"{float(np.mean(r_act)):.3f} -> {float(np.mean(pol.r_actual)):.3f}")
    return pol


def _polish_summary(ctx: StageContext, cfg: Any, pol: Any, before: np.ndarray, runs_per_target: Any,
                    wall: Any, share: np.ndarray) -> dict[str, Any]:
    """``polish.json`` of a pass (or of all passes): ``runs_per_target``/``wall``: the cost before it."""
    from invphys.evaluation.stats import bootstrap_mean_ci

    ev = ctx.spec.evaluation
    m = pol.polished
    after_all = bootstrap_mean_ci(pol.r_actual, ev.bootstrap, ev.confidence, ctx.seed)
    before_all = bootstrap_mean_ci(before, ev.bootstrap, ev.confidence, ctx.seed)
    diff = bootstrap_mean_ci(pol.r_actual - before, ev.bootstrap, ev.confidence, ctx.seed)
    out = {"settings": cfg.key_dump(), "targets": len(m), "polished": int(m.sum()),
            "improved": int((pol.r_actual > before).sum()), "worse": int((pol.r_actual < before).sum()),
            "r_actual_before_mean": before_all[0], "r_actual_before_ci95": list(before_all[1:]),
            "r_actual_after_mean": after_all[0], "r_actual_after_ci95": list(after_all[1:]),
            "diff_mean": diff[0], "diff_ci95": list(diff[1:]),
            "polished_before_mean": float(np.mean(before[m])) if m.any() else None,
            "polished_after_mean": float(np.mean(pol.r_actual[m])) if m.any() else None,
            "simulator_runs": int(pol.runs.sum()), "replayed_runs": pol.replayed_runs, "generations": pol.batches,
            "simulator_s": pol.seconds, "device": pol.device,
            "runs_per_polished_target": float(pol.runs[m].max()) if m.any() else 0.0,
            "simulator_s_per_polished_target": float(share[m].max()) if m.any() else 0.0,
            "total_runs_per_target_max": float(np.max(runs_per_target + pol.runs)),
            "total_wall_s_per_target_max": float(np.max(wall + share))}
    c = pol.confirmed
    if c is not None and cfg.confirm:
        ok = c.pick >= 0
        out["confirm"] = {"repeats": c.repeats, "candidates": cfg.confirm_candidates, "confirmed": int(ok.sum()),
                          "changed": int(c.changed.sum()), "simulator_runs": int(c.runs.sum()),
                          "replayed_runs": c.replayed_runs, "simulator_s": c.seconds,
                          "r_selected_mean": float(np.mean(c.r_selected[ok])) if ok.any() else None,
                          "r_confirmed_mean": float(np.mean(c.r_confirmed[ok])) if ok.any() else None,
                          "targets": [c.record(i) for i in range(len(m))]}
    return out


def _retrain_round(ctx: StageContext, r: int, theta_tr: np.ndarray, y_tr: np.ndarray, added_theta: list[np.ndarray],
                   added_y: list[np.ndarray], rounds: list[dict[str, Any]]) -> Any:
    """Retrain on the training rows plus every simulated round so far; save as ``surrogate_round<r>``."""
    t1 = time.perf_counter()
    surrogate = _retrain(ctx, np.concatenate([theta_tr, *added_theta]), np.concatenate([y_tr, *added_y]))
    surrogate.save(ctx.stage_dir / f"surrogate_round{r}")
    rounds[-1]["retrain_s"] = time.perf_counter() - t1
    return surrogate


def _surrogate_for(ctx: StageContext, r: int, theta_tr: np.ndarray, y_tr: np.ndarray,
                   added_theta: list[np.ndarray], added_y: list[np.ndarray], rounds: list[dict[str, Any]],
                   key: str, best: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> Any:
    """The surrogate round ``r`` proposes with: the saved one, or retrained now (a stop came before it
    was saved); ``best`` given: the checkpoint is rewritten after retraining."""
    path = ctx.stage_dir / f"surrogate_round{r}"
    if "retrain_s" in rounds[-1] and path.is_dir():
        cls = ctx.registry.get("surrogate", (ctx.spec.surrogate or {})["type"])
        return cls.load(path)
    surrogate = _retrain_round(ctx, r, theta_tr, y_tr, added_theta, added_y, rounds)
    if best is not None:
        _save_checkpoint(ctx, key, rounds, best, added_theta, added_y)
    return surrogate


CHECKPOINT_FILE = "progress.npz"


def _checkpoint_key(ctx: StageContext, n: int, feats: np.ndarray, legacy: bool = False) -> str:
    """What a saved round must match to be resumed: everything but ``active.rounds`` and the polish.

    The simulator and features count by their resolved identity (as the dataset store and the validate
    memo key runs: not device, batching or how the spec named the plugin), the validator without its
    ``batch_size`` and ``extract_workers``. ``legacy``: the key as first written (the spec's simulator
    and validator sections verbatim), so rounds saved by earlier versions still resume. Both hold how
    answers are seeded (:data:`~invphys.pipeline.cache.SEEDING`): rounds saved under another seeding (the
    refinements seeded by position, before 2026-11-28) start over instead of resuming.
    """
    from invphys.core.dataset import RunIdentity, extractor_identity
    from invphys.pipeline import cache

    sec = ctx.spec.active.model_dump(mode="json") if ctx.spec.active else {}
    sec.pop("rounds", None)
    sec.pop("polish", None)  # the polish comes after the rounds: its settings do not invalidate them
    common = {"active": sec, "n": n, "targets": np.round(feats, 12).tolist(), "seed": ctx.seed,
              "surrogate": ctx.spec.surrogate, "seeding": cache.SEEDING}
    if legacy:
        return cache.digest({**common, "validator": ctx.spec.validator, "simulator": ctx.spec.simulator,
                       "data": ctx.dataset().fingerprint})
    speed_only = ("batch_size", "extract_workers")
    validator = {k: v for k, v in dict(ctx.spec.validator or {}).items() if k not in speed_only}
    return cache.digest({**common, "validator": validator, "simulator": RunIdentity.of(ctx.simulator()).to_dict(),
                   "features": extractor_identity(ctx.extractor()), "data": ctx.dataset().fingerprint})


def _save_checkpoint(ctx: StageContext, key: str, rounds: list[dict[str, Any]],
                     best: tuple[np.ndarray, np.ndarray, np.ndarray], added_theta: list[np.ndarray],
                     added_y: list[np.ndarray]) -> None:
    """Every finished round's state, written atomically (a killed run resumes after its last round)."""
    import io
    import json

    from invphys.core.atomic import atomic_write_bytes

    buf = io.BytesIO()
    np.savez_compressed(buf, key=np.array(key), rounds=np.array(json.dumps(rounds, default=float)),
                        best_theta=best[0], best_r=best[1], best_y=best[2],
                        added_sizes=np.array([len(a) for a in added_theta], dtype=np.int64),
                        added_theta=np.concatenate(added_theta), added_y=np.concatenate(added_y))
    atomic_write_bytes(ctx.stage_dir / CHECKPOINT_FILE, buf.getvalue())


def _load_checkpoint(ctx: StageContext, keys: tuple[str, ...]) -> dict[str, Any] | None:
    """The saved rounds when they were made with the same settings, i.e. under one of ``keys`` (else
    None: start afresh); ``"key"`` says which."""
    import json

    path = ctx.stage_dir / CHECKPOINT_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            if str(z["key"]) not in keys:
                ctx.log(f"{CHECKPOINT_FILE} was made with other settings; starting from round 0")
                return None
            cuts = np.cumsum(z["added_sizes"])[:-1]
            return {"key": str(z["key"]), "rounds": json.loads(str(z["rounds"])), "best_theta": z["best_theta"],
                    "best_r": z["best_r"], "best_y": z["best_y"], "added_theta": list(np.split(z["added_theta"], cuts)),
                    "added_y": list(np.split(z["added_y"], cuts))}
    except (OSError, ValueError, KeyError) as exc:
        ctx.log(f"{CHECKPOINT_FILE} is unreadable ({exc}); starting from round 0")
        return None
