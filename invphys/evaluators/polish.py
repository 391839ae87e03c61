"""Simulator-in-the-loop polish of answers that were already simulated (``active.polish``).

:func:`polish` runs :func:`~invphys.evaluators.simulator_loop.refine_targets` (ask/tell
CMA-ES on the real simulator, each generation of all targets in one batch) from each target's best
simulated answer, only for targets whose R_actual is below a threshold. The starts' features are
known, so they are not simulated again; a target's answer is the best simulated point, its start
included, so no target gets worse.

:class:`BatchLog` makes it resumable: every simulated batch (points, features, seconds, device) is
appended atomically to an ``.npz`` file; a re-run with the same seeds asks the same points and gets
their features from the log instead of the simulator, so a stopped polish loses at most the batch in
flight, a finished one costs nothing again, and the logged runs still count in the cost.

:func:`confirm` (optional, after a polish) re-simulates each target's best few simulated points a few
times through the same log and answers with the best *mean* R: the polish's R is the best of N runs
of a slightly chaotic simulator, so it is optimistic; the confirmed mean is the R that reproduces.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.safe_read import UserFileError

#: what a polish log says it is (files written before it are recognised by their arrays)
POLISH_LOG_FORMAT = "invphys.polish_log"
POLISH_LOG_VERSION = 1
_LOG_ARRAYS = {"key", "meta", "theta", "y"}


def _log_error(path: Path, problem: str) -> UserFileError:
    return UserFileError("polish log", path, problem)


#: why a log made before polish searches were seeded per target cannot be replayed
OLD_SEEDING = ("it was written by an older invphys, whose polish seeded each target's search by its position in "
               "the target file; this version seeds each target from its own values and cannot replay it: name "
               "another file, or remove this one to polish afresh")


def check_polish_log(path: str | Path, key: str | None = None, replace_other: bool = False,
                     legacy_keys: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """Check, before anything is simulated, that ``path`` can be a polish log; return its logged batches.

    Refused with one :class:`~invphys.core.errors.InvphysError` line naming the file: a directory, a
    symbolic link, a parent that is a file or not writable, a read-only file, and an existing file that is
    not a polish log written by invphys (a user's CSV is never overwritten) or is truncated or corrupt.
    ``key`` (None: not checked yet): a log made for another bundle, target set or settings is refused too,
    unless ``replace_other`` (a log in invphys's own stage directory), when it counts as empty.
    ``legacy_keys``: the keys the same polish had under the older, position-seeded searches (refused
    with :data:`OLD_SEEDING`: their batches are not this version's).
    """
    p = Path(path)
    if p.is_symlink():
        raise _log_error(p, "it is a symbolic link; name a regular file (e.g. polish.npz)")
    if p.is_dir():
        raise _log_error(p, "it is a directory; name a file (e.g. polish.npz)")
    _check_parent(p)
    if not p.exists():
        return []
    if not os.access(p, os.W_OK):
        raise _log_error(p, "it is read-only; name another file")
    batches, logged_key = _read_log(p)
    if key is None or logged_key == key:
        return batches
    if replace_other:
        return []
    if logged_key in legacy_keys:
        raise _log_error(p, OLD_SEEDING)
    raise _log_error(p, "it was made for another bundle, target set or polish settings; name another file, "
                        "or remove this one to polish afresh")


def _check_parent(p: Path) -> None:
    """The nearest existing folder above ``p`` is a folder the log (and its folders) can be written in."""
    parent = p.absolute().parent
    while not parent.exists() and not parent.is_symlink() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise _log_error(p, f"{str(parent)!r} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise _log_error(p, f"cannot write in {str(parent)!r} (permission denied)")


def _read_log(p: Path) -> tuple[list[dict[str, Any]], str]:
    """The batches and key of the polish log ``p`` (bounded reader); anything else is refused."""
    from invphys.core import safe_read

    safe_read.check_regular_file(p, what="polish log", max_bytes=safe_read.NPZ_MAX_BYTES)
    try:
        with open(p, "rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise _log_error(p, f"cannot read it: {exc.strerror or exc}") from None
    if magic != b"PK\x03\x04":  # not even a zip archive: somebody's own file
        raise _log_error(p, "it exists and is not a polish log written by invphys; refusing to overwrite it "
                            "(name another file)")
    z = safe_read.load_user_npz(p, what="polish log")
    if not _LOG_ARRAYS <= set(z) <= _LOG_ARRAYS | {"format", "version"} or (
            "format" in z and str(z["format"]) != POLISH_LOG_FORMAT):
        raise _log_error(p, "it exists and is not a polish log written by invphys; refusing to overwrite it "
                            "(name another file)")
    try:
        if "version" in z and int(z["version"]) > POLISH_LOG_VERSION:
            raise _log_error(p, f"format version {int(z['version'])} is newer than this invphys reads; upgrade")
        meta = safe_read.loads_user_json(str(z["meta"]), source="meta")
        runs = [int(m["runs"]) for m in meta]
        theta, y = np.asarray(z["theta"], np.float64), np.asarray(z["y"], np.float64)
        if theta.ndim != 2 or y.ndim != 2 or len(theta) != sum(runs) or len(y) != len(theta) or min(runs, default=1) < 0:
            raise ValueError("its arrays do not match its batches")
        cuts = np.cumsum(runs)[:-1]
        batches = [{"runs": r, "seconds": float(m["seconds"]), "device": str(m["device"]), "theta": t, "y": v}
                   for r, m, t, v in zip(runs, meta, np.split(theta, cuts), np.split(y, cuts), strict=True)]
    except UserFileError:
        raise
    except (InvphysError, ValueError, TypeError, KeyError) as exc:
        raise _log_error(p, f"corrupt polish log ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); "
                            "move it away or name another file") from None
    return batches, str(z["key"])


class BatchLog:
    """Memoised batches of a deterministic search: replay the logged ones, simulate and log the rest.

    ``evaluator`` is a :class:`~invphys.evaluators.simulator_loop.SimulatorEvaluator` (or
    anything with ``__call__``, ``wall_time_s`` and ``device``). Batch ``i`` of a run is replayed when
    the logged batch ``i`` has the same points (within ``atol``); the first mismatch drops the rest of
    the log (the search diverged) and simulates from there. ``key`` names what the log was made for: a
    log made for another key is refused (:func:`check_polish_log`; with ``replace_other``, e.g. a log
    in a pipeline stage's own directory, it starts an empty log instead; a key of ``legacy_keys`` is
    refused as older seeding). An existing file that is not
    a polish log, or a truncated one, is refused and never overwritten; the log is written atomically.
    ``chunk``: a call with more points is simulated and logged in chunks of that many (a stop loses at
    most one chunk). ``on_batch(runs, replayed)`` is called after each batch (progress bars).
    """

    def __init__(self, path: Path | None, key: str, evaluator: Any,
                 log: Callable[[str], None] | None = None, atol: float = 1e-9, chunk: int | None = None,
                 on_batch: Callable[[int, bool], None] | None = None, replace_other: bool = False,
                 legacy_keys: tuple[str, ...] = ()) -> None:
        self.path, self.key, self.evaluator, self.atol, self.chunk = path, key, evaluator, atol, chunk
        self._log = log or (lambda _msg: None)
        self._on_batch = on_batch or (lambda _runs, _replayed: None)
        self.batches: list[dict[str, Any]] = []
        if path is not None:
            self.batches = check_polish_log(path, key, replace_other=replace_other, legacy_keys=legacy_keys)
            if replace_other and Path(path).is_file() and not self.batches:
                self._log(f"{Path(path).name} was made for other settings; polishing afresh")
        self.calls = 0
        self.runs = 0
        self.replayed_runs = 0
        self.seconds = 0.0
        self.device = ""

    def _save(self) -> None:
        if self.path is None:
            return
        from invphys.core.atomic import atomic_write_bytes

        meta = [{k: b[k] for k in ("runs", "seconds", "device")} for b in self.batches]
        buf = io.BytesIO()
        np.savez_compressed(buf, format=np.array(POLISH_LOG_FORMAT), version=np.array(POLISH_LOG_VERSION),
                            key=np.array(self.key), meta=np.array(json.dumps(meta)),
                            theta=np.concatenate([b["theta"] for b in self.batches]),
                            y=np.concatenate([b["y"] for b in self.batches]))
        try:
            atomic_write_bytes(Path(self.path), buf.getvalue())
        except OSError as exc:
            raise _log_error(Path(self.path), f"cannot write it: {exc.strerror or exc}") from None

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_2d(np.asarray(theta, dtype=np.float64))
        step = self.chunk or len(theta) or 1
        return np.concatenate([self._batch(theta[a:a + step]) for a in range(0, max(len(theta), 1), step)])

    def _batch(self, theta: np.ndarray) -> np.ndarray:
        i = self.calls
        self.calls += 1
        if i < len(self.batches):
            b = self.batches[i]
            if b["theta"].shape == theta.shape and np.allclose(b["theta"], theta, rtol=0.0, atol=self.atol):
                self.runs += len(theta)
                self.replayed_runs += len(theta)
                self.seconds += float(b["seconds"])
                self.device = b["device"] or self.device
                self._log(f"polish batch {i}: {len(theta)} runs replayed from {Path(str(self.path)).name}")
                self._on_batch(len(theta), True)
                return np.array(b["y"], dtype=np.float64)
            self._log(f"polish batch {i}: the search asked other points than logged; simulating from here")
            del self.batches[i:]
        s0 = self.evaluator.wall_time_s
        y = np.asarray(self.evaluator(theta), dtype=np.float64)
        seconds = float(self.evaluator.wall_time_s - s0)
        self.runs += len(theta)
        self.seconds += seconds
        self.device = getattr(self.evaluator, "device", "") or self.device
        self.batches.append({"runs": len(theta), "seconds": seconds, "device": self.device,
                             "theta": theta.copy(), "y": y.copy()})
        self._save()
        self._log(f"polish batch {i}: {len(theta)} runs simulated in {seconds:.1f} s")
        self._on_batch(len(theta), False)
        return y


@dataclass
class Polished:
    """The polish's outcome for all targets (unpolished ones unchanged, 0 runs)."""

    theta: np.ndarray
    r_actual: np.ndarray
    features: np.ndarray
    runs: np.ndarray  # new simulator runs per target
    polished: np.ndarray  # bool mask
    seconds: float  # simulator seconds in all (replayed batches included)
    batches: int
    replayed_runs: int
    device: str
    #: per target: every point simulated for it (theta (n, d), score (n,), features (n, M)), its start
    #: first; None for a target that was not polished (its answer is its only simulated point)
    points: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] | None = None
    #: what :func:`confirm` did (None: not confirmed); its answers are already in theta/r_actual/features
    confirmed: Confirmed | None = None


def polish(targets: np.ndarray, theta: np.ndarray, r_actual: np.ndarray, features: np.ndarray,
           scales: np.ndarray, evaluate: Any, budget: int, popsize: int = 8, sigma0: float = 0.05,
           below: float = 0.95, seed: int = 0,
           score: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
           seeds: Any = None) -> Polished:
    """CMA-ES on the simulator from each answer with ``r_actual < below`` (``budget`` new runs each).

    ``evaluate``: a :class:`BatchLog` or a ``SimulatorEvaluator`` (features of normalised points,
    NaN rows for failures). A start whose ``features`` are not finite is simulated first (1 run).
    ``score(features (B, M), targets (B, M)) -> (B,)`` scores points and must match how ``r_actual``
    was computed (default: R_gt with kappa 3 over every feature; the inverter passes a masked R).
    ``seeds``: one seed per target (default: from ``seed`` and each target's values,
    :func:`~invphys.evaluators.simulator_loop.target_seeds`); a target's search never depends on its
    position or on the other targets.
    """
    from invphys.evaluators.simulator_loop import refine_targets

    theta, r_actual = np.array(theta, dtype=np.float64), np.array(r_actual, dtype=np.float64)
    features = np.array(features, dtype=np.float64)
    n = len(theta)
    mask = ~(r_actual >= below)  # NaN / -inf (never simulated successfully) are polished too
    idx = np.flatnonzero(mask)
    runs = np.zeros(n, dtype=np.int64)
    seconds0 = float(getattr(evaluate, "seconds", getattr(evaluate, "wall_time_s", 0.0)))
    if len(idx) == 0:
        return Polished(theta, r_actual, features, runs, mask, 0.0, 0, 0, "")
    known = features[idx]
    resim = ~np.all(np.isfinite(known), axis=1)
    calls = [0]

    def ev(points: np.ndarray) -> np.ndarray:
        calls[0] += 1
        if calls[0] > 1:
            return evaluate(points)
        out = known.copy()  # the starts: already simulated (their features are the answers' features)
        if resim.any():
            out[resim] = evaluate(points[resim])
        return out

    targets = np.asarray(targets, dtype=np.float64)
    refined = refine_targets(targets[idx], theta[idx], scales, ev, budget + 1, popsize, sigma0, seed=seed, score=score,
                             keep=True, seeds=None if seeds is None else [int(seeds[i]) for i in idx])
    points: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = [None] * n
    for j, (i, x) in enumerate(zip(idx, refined, strict=True)):
        points[i] = x.points
        runs[i] = x.evaluated - 1 + int(resim[j])
        if x.features is None or not np.all(np.isfinite(x.features)):
            continue
        r_new = x.score  # refine_targets scored it with ``score`` (default: the same R_gt as r_actual)
        if r_new > r_actual[i] or not np.isfinite(r_actual[i]):
            theta[i], r_actual[i], features[i] = x.theta, r_new, x.features
    seconds = float(getattr(evaluate, "seconds", getattr(evaluate, "wall_time_s", 0.0))) - seconds0
    return Polished(theta, r_actual, features, runs, mask, seconds, calls[0] - 1 + int(resim.any()),
                    int(getattr(evaluate, "replayed_runs", 0)), str(getattr(evaluate, "device", "") or ""), points)


@dataclass
class Confirmed:
    """What :func:`confirm` did, per target (``C_t`` candidates of target ``t``, ``repeats`` re-runs each).

    ``theta``/``r_actual``/``features`` are the answers: each target's candidate with the best mean R
    over its re-runs, that mean as its R (``r_confirmed``), and the features of the run that found it.
    ``r_selected``: the polish's answer's R (best of N single runs). ``candidates[t]`` (C_t, d): the
    re-simulated points, the polish's answer first; ``selected[t]`` (C_t,): each one's R from the run
    that found it; ``values[t]`` (C_t, repeats): the R of every re-run (NaN: the run failed, counted as
    R 0 in the mean). ``pick[t]``: the answer's index among the candidates (-1: nothing to confirm, the
    target never simulated successfully; its answer is left as it was).
    """

    theta: np.ndarray
    r_actual: np.ndarray
    features: np.ndarray
    r_selected: np.ndarray
    candidates: list[np.ndarray]
    selected: list[np.ndarray]
    values: list[np.ndarray]
    pick: np.ndarray
    runs: np.ndarray  # re-runs per target (candidates x repeats)
    repeats: int
    seconds: float
    replayed_runs: int
    device: str

    @property
    def r_confirmed(self) -> np.ndarray:
        return self.r_actual

    @property
    def changed(self) -> np.ndarray:
        """Targets whose answer is not the polish's (best-of-N) answer."""
        return self.pick > 0

    def means(self, t: int) -> np.ndarray:
        """Mean R of each of target ``t``'s candidates over its re-runs (a failed run counts as 0)."""
        return np.nan_to_num(self.values[t], nan=0.0).mean(axis=1) if self.values[t].size else np.zeros(0)

    def record(self, t: int) -> dict[str, Any]:
        """Target ``t``'s confirmation as JSON-able values (None for NaN)."""
        def f(v: Any) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {"repeats": self.repeats, "candidates": len(self.candidates[t]), "pick": int(self.pick[t]),
                "changed": bool(self.changed[t]), "r_selected": f(self.r_selected[t]),
                "r_confirmed": f(self.r_actual[t]) if self.pick[t] >= 0 else None,
                "candidate_r_selected": [f(v) for v in self.selected[t]],
                "candidate_r_mean": [f(v) for v in self.means(t)],
                "run_r": [[f(v) for v in row] for row in self.values[t]],
                "runs": int(self.runs[t])}

    def apply(self, pol: Polished) -> Polished:
        """``pol`` with the confirmed answers, and the re-runs added to its runs and seconds."""
        from dataclasses import replace

        return replace(pol, theta=self.theta.copy(), r_actual=self.r_actual.copy(), features=self.features.copy(),
                       runs=pol.runs + self.runs, seconds=pol.seconds + self.seconds,
                       replayed_runs=pol.replayed_runs + self.replayed_runs, device=self.device or pol.device,
                       confirmed=self)


def confirm(pol: Polished, targets: np.ndarray, scales: np.ndarray, evaluate: Any, repeats: int,
            candidates: int = 4, score: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
            kappa: float = 3.0) -> Confirmed:
    """Re-simulate each target's best ``candidates`` points ``repeats`` times; answer with the best mean.

    The simulator is slightly chaotic: the polish's answer is the best of N single runs, so its R is
    optimistic (re-simulated, most answers reproduce but a few drop a lot). Each target's candidates are
    its polish's answer and the next best distinct points the polish simulated for it, by the R of the
    run that found them (a target that was not polished has one candidate: its answer). Every
    candidate of every target is simulated ``repeats`` more times, all in one ``evaluate`` call
    (through the polish's :class:`BatchLog`, it is logged and replayed like the search; re-run ``k`` of
    every candidate comes before re-run ``k + 1`` of any); the answer is the candidate with the best
    mean R over these new runs (ties: the earlier candidate, so the polish's answer), and that mean is
    its R. The run that selected a candidate is *not* in its mean (it is the best-of-N draw the
    confirmation is there to correct). The mean is still slightly optimistic, as the same re-runs
    choose among the candidates, but far less than best-of-N. A failed re-run counts as R 0.

    ``score`` must be the polish's (default R_gt with ``kappa``); targets may hold NaN for features
    that ``score`` ignores. Cost: ``repeats`` x (number of candidates) runs per target.
    """
    from invphys.core.objectives import recovery_reward

    if repeats < 1 or candidates < 1:
        raise InvphysError(f"confirm: repeats and candidates must be >= 1, got {repeats} and {candidates}")
    score = score or (lambda y, t: recovery_reward(y, t, scales, kappa))
    targets = np.asarray(targets, dtype=np.float64)
    n = len(pol.theta)
    cands: list[np.ndarray] = []
    sel: list[np.ndarray] = []
    feats: list[np.ndarray] = []
    for i in range(n):
        answer = (pol.theta[i][None, :], np.array([pol.r_actual[i]], dtype=np.float64), pol.features[i][None, :])
        pts = (pol.points[i] if pol.points is not None else None) or answer
        ok = np.isfinite(pts[1]) & np.all(np.isfinite(pts[2]), axis=1)
        th, sc, fe = pts[0][ok], pts[1][ok], pts[2][ok]
        first = [j for j in range(len(th)) if np.array_equal(th[j], pol.theta[i])]
        if first:
            order = [first[0]]
        elif np.isfinite(answer[1][0]) and np.all(np.isfinite(answer[2])):  # not among the points: add it
            th, sc, fe = (np.concatenate([a, b]) for a, b in zip(answer, (th, sc, fe), strict=True))
            order = [0]
        else:
            order = []
        for j in np.argsort(-sc, kind="stable"):
            if len(order) >= candidates:
                break
            if not any(np.array_equal(th[j], th[k]) for k in order):
                order.append(int(j))
        cands.append(th[order].reshape(len(order), -1))
        sel.append(sc[order])
        feats.append(fe[order].reshape(len(order), -1))
    sizes = np.array([len(c) for c in cands], dtype=np.int64)
    owners = np.repeat(np.arange(n), sizes)
    seconds0 = float(getattr(evaluate, "seconds", getattr(evaluate, "wall_time_s", 0.0)))
    replayed0 = int(getattr(evaluate, "replayed_runs", 0))
    values = [np.zeros((s, repeats)) for s in sizes]
    if sizes.sum():
        flat = np.concatenate(cands)
        y = np.asarray(evaluate(np.tile(flat, (repeats, 1))), dtype=np.float64)
        r = np.asarray(score(y, targets[np.tile(owners, repeats)]), dtype=np.float64)
        r = np.where(np.all(np.isfinite(y), axis=1) & np.isfinite(r), r, np.nan).reshape(repeats, -1).T
        values = np.split(r, np.cumsum(sizes)[:-1])
    theta, r_act, features = pol.theta.copy(), pol.r_actual.copy(), pol.features.copy()
    pick = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        if sizes[i] == 0:
            continue
        means = np.nan_to_num(values[i], nan=0.0).mean(axis=1)
        pick[i] = int(np.argmax(means))
        theta[i], r_act[i], features[i] = cands[i][pick[i]], means[pick[i]], feats[i][pick[i]]
    seconds = float(getattr(evaluate, "seconds", getattr(evaluate, "wall_time_s", 0.0))) - seconds0
    return Confirmed(theta, r_act, features, np.array(pol.r_actual, dtype=np.float64), cands, sel, list(values),
                     pick, sizes * repeats, repeats, seconds, int(getattr(evaluate, "replayed_runs", 0)) - replayed0,
                     str(getattr(evaluate, "device", "") or ""))
