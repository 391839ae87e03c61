"""How the surrogate's ceiling for amortised answers grows with training rows (a learning curve of the CEILING).

    nice -n 10 python benchmarks/bench_surrogate_ceiling.py --bundle inverters/orange_peel_paper_all \\
        --sets test=@test uniform=datasets/orange_peel_paper_fresh_uniform \\
               edge=datasets/orange_peel_paper_fresh_edge \\
        --sizes 750 1500 3000 6000 9000 12500 --extra-train datasets/orange_peel_paper_faces \\
        --variant "wide={hidden: [256, 256, 128]}" "long={max_epochs: 400, patience: 400}" "ten={members: 10}" \\
        --goal test=0.92 uniform=0.92 edge=0.88 --plot docs/orange-peel/surrogate-ceiling.png \\
        --out benchmarks/results/surrogate_ceiling_paper_cpu.json

An amortised answer is chosen by the surrogate, so it can only be as good as the surrogate is at the answer.
The CEILING of a set of targets is the mean recovery ``R`` (``masked_recovery`` with the bundle's scales and
kappa, the score every answer gets) of the surrogate's predicted features at the targets' TRUE parameters
against their real (simulated) features: the R a perfect search over the surrogate would be credited with if
it returned the truth. It bounds what the surrogate can tell apart, not what an answer scores.

Training rows are the bundle's own (``data/train.npz``); ``--sizes`` takes nested subsets of them (one seeded
permutation, the first n rows, kept in the bundle's order, so the largest size equal to all rows is exactly
the bundle's training input). Each size trains the bundle's surrogate (its ``surrogate/model.json`` settings;
``--members``/``--max-epochs`` override them, ``--small-members``/``--small-max-epochs`` only below
``--small-below`` rows) and is scored on every ``--sets`` entry (``NAME=STORE``, ``NAME=@test`` for the
bundle's held-out rows): held-out R^2 per feature and mean, each feature's share of the mean squared scaled
error (what pulls R down), and the ceiling, with bootstrap 95 % intervals
over the set's rows. ``--extra-train STORE ...`` adds one more point: all training rows plus those stores' rows.
``--variant NAME='{setting: value}'`` adds a point on all training rows (with ``--variants-on-extra``: plus the
extra rows) with changed surrogate settings (the
architecture lever against the rows lever). The shipped surrogate is scored too (``shipped``). A power law ``1 - ceiling = a n^-b`` is fitted per set
over the sizes (and over the three largest) and solved for the rows that would reach ``--goal NAME=R``, with a
bootstrap interval. The JSON is rewritten after every
point, so an interrupted run keeps what it measured; ``--plot PNG`` draws the curves.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))


def ceiling_rows(predict: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, y: np.ndarray,
                 scales: np.ndarray, kappa: float) -> np.ndarray:
    """(N,) recovery R of ``predict(theta)`` (the features predicted at the TRUE parameters) against ``y``."""
    from invphys.core.masked_recovery import masked_recovery

    return masked_recovery(np.asarray(predict(theta), dtype=np.float64), y, scales, None, kappa)


def r2_per_feature(pred: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(M,) coefficient of determination of each feature."""
    ss = ((y - y.mean(0)) ** 2).sum(0)
    return 1 - ((pred - y) ** 2).sum(0) / np.maximum(ss, 1e-300)


def score_set(pred: np.ndarray, theta: np.ndarray, y: np.ndarray, scales: np.ndarray, kappa: float,
              names: list[str], boot: int, seed: int) -> dict[str, Any]:
    """Ceiling and held-out R^2 of predictions ``pred`` (made at ``theta``) on one set, with bootstrap 95 % CIs."""
    r = ceiling_rows(lambda _: pred, theta, y, scales, kappa)
    r2 = r2_per_feature(pred, y)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(y), size=(boot, len(y)))
    bc = r[idx].mean(1)
    br2 = np.array([r2_per_feature(pred[i], y[i]).mean() for i in idx])

    z2 = (((pred - y) / scales) ** 2).mean(0)

    def ci(v: np.ndarray) -> list[float]:
        return [float(np.percentile(v, 2.5)), float(np.percentile(v, 97.5))]

    return {"n": len(y), "ceiling": float(r.mean()), "ceiling_ci95": ci(bc), "ceiling_median": float(np.median(r)),
            "ceiling_p10": float(np.percentile(r, 10)), "r2_mean": float(r2.mean()), "r2_mean_ci95": ci(br2),
            "r2_per_feature": dict(zip(names, (float(v) for v in r2), strict=True)),
            "error_share": dict(zip(names, (float(v) for v in z2 / max(z2.sum(), 1e-300)), strict=True))}


def load_set(bundle: Any, spec: str) -> tuple[str, np.ndarray, np.ndarray]:
    """``NAME=STORE`` or ``NAME=@test`` -> (name, theta, y), finite rows only."""
    from invphys.core.errors import InvphysError

    name, eq, path = spec.partition("=")
    if not eq or not name or not path:
        raise InvphysError(f"--sets wants NAME=STORE or NAME=@test, got {spec!r}")
    theta, y = bundle.data("test") if path == "@test" else store_rows(path)
    ok = np.all(np.isfinite(y), axis=1)
    return name, np.asarray(theta[ok], dtype=np.float64), np.asarray(y[ok], dtype=np.float64)


def store_rows(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(theta, y) of a dataset store's successful rows (normalised parameters, features)."""
    from invphys.core.dataset import DatasetStore
    from invphys.core.errors import InvphysError

    if not Path(path).is_dir():
        raise InvphysError(f"no dataset store at {path!r}")
    a = DatasetStore(path).arrays(ok_only=True)
    return np.asarray(a.theta, dtype=np.float64), np.asarray(a.y, dtype=np.float64)


def surrogate_settings(bundle_root: Path, members: int | None, max_epochs: int | None) -> dict[str, Any]:
    """The bundle surrogate's plugin block (``surrogate/model.json``), with the given overrides."""
    from invphys.core.errors import InvphysError

    try:
        doc = json.loads((bundle_root / "surrogate" / "model.json").read_text())
        block = {"type": doc["plugin"], **doc["config"]}
    except (OSError, ValueError, KeyError) as exc:
        raise InvphysError(f"{bundle_root}: cannot read the surrogate's settings ({exc})") from None
    if members is not None:
        block["members"] = members
    if max_epochs is not None:
        block["max_epochs"] = max_epochs
        block["patience"] = min(int(block.get("patience", max_epochs)), max_epochs)
    return block


def train(block: dict[str, Any], theta: np.ndarray, y: np.ndarray) -> tuple[Any, float]:
    """Fit the surrogate plugin ``block`` on (theta, y) as the train stage does (its own validation carves)."""
    from invphys import registry

    sur = registry.default_registry().create("surrogate", dict(block))
    t0 = time.perf_counter()
    sur.fit(theta, y, progress=False)
    return sur, time.perf_counter() - t0


def power_law(ns: list[int], ceilings: list[float], goal: float | None) -> dict[str, Any] | None:
    """Least-squares fit of ``log(1 - c) = log a - b log n``; the rows it says reach ``goal`` (None: never)."""
    pts = [(n, c) for n, c in zip(ns, ceilings, strict=True) if c < 1]
    if len(pts) < 2:
        return None
    x = np.log([p[0] for p in pts])
    g = np.log([1 - p[1] for p in pts])
    slope, icpt = np.polyfit(x, g, 1)
    out: dict[str, Any] = {"a": float(np.exp(icpt)), "b": float(-slope), "points": len(pts)}
    if goal is not None:
        out["goal"] = goal
        out["rows_to_goal"] = (float(np.exp((icpt - np.log(1 - goal)) / -slope)) if slope < 0 else None)
    return out


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, timeout=30).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--bundle", required=True, help="inverter bundle: training rows, scales, kappa, surrogate settings")
    p.add_argument("--sets", nargs="+", required=True, help="NAME=STORE or NAME=@test (the bundle's held-out rows)")
    p.add_argument("--sizes", nargs="+", type=int, required=True, help="nested training-subset sizes")
    p.add_argument("--extra-train", nargs="+", default=None,
                   help="STORE(s) whose rows are added to ALL training rows (one point)")
    p.add_argument("--members", type=int, default=None, help="ensemble members (default: the bundle's)")
    p.add_argument("--max-epochs", type=int, default=None, help="epochs (default: the bundle's)")
    p.add_argument("--small-below", type=int, default=0, help="sizes below this use --small-members/--small-max-epochs")
    p.add_argument("--small-members", type=int, default=None)
    p.add_argument("--small-max-epochs", type=int, default=None)
    p.add_argument("--goal", nargs="*", default=[], help="NAME=R: rows the power law says reach R on set NAME")
    p.add_argument("--variants-on-extra", action="store_true",
                   help="variant points train on all training rows plus the --extra-train rows")
    p.add_argument("--variant", nargs="*", default=[],
                   help="NAME='{setting: value}': one more point on all training rows with these surrogate settings")
    p.add_argument("--plot", default=None, help="PNG: ceiling against training rows, one line per set")
    p.add_argument("--bootstrap", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0, help="the subsets' permutation and the bootstrap")
    p.add_argument("--out", required=True)
    return p.parse_args(argv)


def plan(a: argparse.Namespace, n_train: int) -> list[dict[str, Any]]:
    """Every training point, smallest first: label, base rows, members, epochs, extra rows or not, settings."""
    import yaml

    from invphys.core.errors import InvphysError

    bad = [n for n in a.sizes if not 2 <= n <= n_train]
    if bad:
        raise InvphysError(f"--sizes must lie in [2, {n_train}] (the bundle's training rows), got {bad}")
    full = {"members": a.members, "max_epochs": a.max_epochs, "extra": False, "update": {}}
    pts = []
    for n in sorted(set(a.sizes)):
        small = n < a.small_below
        pts.append({**full, "label": f"n={n}", "base_rows": n,
                    "members": a.small_members if small and a.small_members else a.members,
                    "max_epochs": a.small_max_epochs if small and a.small_max_epochs else a.max_epochs})
    if a.extra_train:
        pts.append({**full, "label": f"n={n_train}+extra", "base_rows": n_train, "extra": True})
    on_extra = bool(a.extra_train) and a.variants_on_extra
    for v in a.variant:
        name, _, text = v.partition("=")
        try:
            update = yaml.safe_load(text)
        except yaml.YAMLError:
            update = None
        if not name or not isinstance(update, dict):
            raise InvphysError(f"--variant wants NAME='{{setting: value, ...}}', got {v!r}")
        pts.append({**full, "label": f"n={n_train}{'+extra' if on_extra else ''}:{name}", "base_rows": n_train,
                    "update": update, "extra": on_extra})
    return pts


def run(a: argparse.Namespace) -> dict[str, Any]:
    """Every point of the curve (module docstring); writes ``a.out`` after each."""
    import _machine

    from invphys.core.errors import InvphysError
    from invphys.inverter.bundle import Bundle

    b = Bundle(a.bundle)
    names = list(b.feature_names)
    tt, ty = b.data("train")
    ok = np.all(np.isfinite(ty), axis=1)
    tt, ty = np.asarray(tt[ok], dtype=np.float64), np.asarray(ty[ok], dtype=np.float64)
    goals = {}
    for g in a.goal:
        k, _, v = g.partition("=")
        try:
            goals[k] = float(v)
        except ValueError:
            raise InvphysError(f"--goal wants NAME=R, got {g!r}") from None
    sets = [load_set(b, s) for s in a.sets]
    extra = None
    if a.extra_train:
        parts = [store_rows(path) for path in a.extra_train]
        extra = (np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts]))
    if extra is not None:
        keep = np.all(np.isfinite(extra[1]), axis=1)
        extra = (extra[0][keep], extra[1][keep])
    points = plan(a, len(tt))
    perm = np.random.default_rng(a.seed).permutation(len(tt))
    out: dict[str, Any] = {
        "benchmark": "surrogate_ceiling", **_machine.provenance(), "device": f"cpu ({_machine.cpu_name()})",
        "git_commit": git_commit(), "bundle": a.bundle, "train_rows": len(tt), "extra_train": (a.extra_train[0] if a.extra_train and len(a.extra_train) == 1
                                                      else a.extra_train),
        "extra_rows": 0 if extra is None else len(extra[0]), "kappa": b.kappa, "scales": b.scales.tolist(),
        "settings": {"surrogate": surrogate_settings(Path(a.bundle), a.members, a.max_epochs), "seed": a.seed,
                     "bootstrap": a.bootstrap, "subsets": "nested: first n rows of one seeded permutation, "
                     "kept in the bundle's order", "small_below": a.small_below,
                     "small_members": a.small_members, "small_max_epochs": a.small_max_epochs},
        "sets": {name: {"store": s.partition("=")[2], "n": len(y)} for (name, _, y), s in zip(sets, a.sets,
                                                                                             strict=True)},
        "shipped": {name: score_set(b.surrogate.predict(th), th, y, b.scales, b.kappa, names, a.bootstrap, a.seed)
                    for name, th, y in sets},
        "points": []}
    _write(out, a.out)
    curve: list[tuple[int, dict[str, np.ndarray]]] = []
    for pt in points:
        block = {**surrogate_settings(Path(a.bundle), pt["members"], pt["max_epochs"]), **pt["update"]}
        idx = np.sort(perm[: pt["base_rows"]])
        th, y = tt[idx], ty[idx]
        if pt["extra"] and extra is not None:
            th, y = np.concatenate([th, extra[0]]), np.concatenate([y, extra[1]])
        sur, secs = train(block, th, y)
        res = {name: score_set(sur.predict(st), st, sy, b.scales, b.kappa, names, a.bootstrap, a.seed)
               for name, st, sy in sets}
        out["points"].append({"label": pt["label"], "rows": len(th), "base_rows": pt["base_rows"],
                              "members": block["members"], "max_epochs": block["max_epochs"],
                              "settings_changed": pt["update"], "train_s": secs, "sets": res})
        print(f"{pt['label']:>16s} ({len(th)} rows, {block['members']} members, {block['max_epochs']} epochs, "
              f"{secs:.0f} s): " + ", ".join(f"{k} R {v['ceiling']:.3f} R2 {v['r2_mean']:.3f}" for k, v in res.items()),
              file=sys.stderr)
        if pt["label"] == f"n={len(th)}":
            curve.append((len(th), {name: ceiling_rows(sur.predict, st, sy, b.scales, b.kappa) for name, st, sy in sets}))
            out["power_law"] = fits(curve, goals, a.bootstrap, a.seed)
        _write(out, a.out)
    if a.plot:
        plot(out, a.plot)
    return out


def fits(curve: list[tuple[int, dict[str, np.ndarray]]], goals: dict[str, float], boot: int,
         seed: int) -> dict[str, Any]:
    """Per set, the power law over every plain size (``all``) and over the three largest (``last3``: the local
    slope), each with a bootstrap 95 % interval of its rows to the goal (targets resampled jointly over sizes;
    None: never reached)."""
    if len(curve) < 2:
        return {}
    out: dict[str, Any] = {}
    for name in curve[0][1]:
        entry = {}
        for key, part in (("all", curve), ("last3", curve[-3:])):
            ns = [n for n, _ in part]
            fit = power_law(ns, [float(r[name].mean()) for _, r in part], goals.get(name))
            if fit is not None and fit.get("goal") is not None and boot:
                m = len(part[0][1][name])
                idx = np.random.default_rng(seed).integers(0, m, size=(boot, m))
                cs = np.stack([r[name][idx].mean(1) for _, r in part], axis=1)
                got = [power_law(ns, list(c), fit["goal"]) for c in cs]
                v = np.array([np.inf if g is None or g["rows_to_goal"] is None else g["rows_to_goal"] for g in got])
                fit["rows_to_goal_ci95"] = [float(q) if np.isfinite(q) else None
                                            for q in np.percentile(v, [2.5, 97.5])]
            entry[key] = fit
        out[name] = entry
    return out


def plot(rec: dict[str, Any], path: str) -> None:
    """Ceiling (bootstrap 95 % band) against training rows per set, the shipped surrogate, the extra and
    variant points, and the fitted power laws."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    plain = [p for p in rec["points"] if p["label"] == f"n={p['rows']}"]
    others = [p for p in rec["points"] if p not in plain]
    for k, name in enumerate(rec["sets"]):
        color = f"C{k}"
        ns = np.array([p["rows"] for p in plain])
        c = np.array([p["sets"][name]["ceiling"] for p in plain])
        lo, hi = (np.array([p["sets"][name]["ceiling_ci95"][j] for p in plain]) for j in (0, 1))
        ax.plot(ns, c, "o-", color=color, label=f"{name} ({rec['sets'][name]['n']} targets)")
        ax.fill_between(ns, lo, hi, color=color, alpha=0.15)
        fit = ((rec.get("power_law") or {}).get(name) or {}).get("all")
        for style, f in ((":", fit), ("-.", ((rec.get("power_law") or {}).get(name) or {}).get("last3"))):
            if f:
                grid = np.geomspace(ns.min(), max(ns.max() * 8, min(f.get("rows_to_goal") or 0, 3e5) * 1.2), 100)
                ax.plot(grid, 1 - f["a"] * grid ** -f["b"], style, color=color, lw=1)
        if fit and fit.get("goal") is not None:
            ax.axhline(fit["goal"], color=color, lw=0.8, ls="--")
        for m, p in zip("s^Dv", others, strict=False):
            ax.plot(p["rows"], p["sets"][name]["ceiling"], m, color=color, mfc="none", ms=8,
                    label=p["label"].split("n=", 1)[1] if k == 0 else None)
    ax.set_xscale("log")
    ax.set_xlabel("training rows")
    ax.set_ylabel("ceiling: mean R of the surrogate at the true parameters")
    ax.set_title("Surrogate ceiling against training rows\n(dotted: power law on all sizes, dash-dot: on the "
                 "three largest; dashed: goal)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _write(out: dict[str, Any], path: str) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(out, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    from invphys.core.errors import InvphysError

    a = parse_args(argv)
    try:
        run(a)
    except InvphysError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
