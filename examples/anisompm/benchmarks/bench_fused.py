"""The fused substep (``taichi_fused``: one G2P2G kernel and one grid kernel per substep) against the plain
one (clear, p2g, grid update, g2p) on the Taichi backend: same state, same features, how much faster (issue 52).

On ``--runs`` random parameter vectors (seed 0) of the orange peel at ``--preset``, one warm simulator per way
(``--ways``: plain; fused, g2p's state kept in registers; fused_stored, that state written back and read again):

1. **state parity**: each backend loads the first ``--batch`` runs, sets the same moving, strained, partly
   damaged state (``bench_tiled_p2g.perturbed_state``) and advances ``--parity-steps`` substeps; the particles'
   largest difference from plain, and plain's from plain again (GPU float atomics differ run to run);
2. **kernel profile**: seconds per launch of each stage (``kernel_times``: plain clear/p2g/grid/g2p, fused
   fused/fgrid) and their sum per substep;
3. **whole runs**: the same runs each way, then each way again (the simulator's scheduling: continuous
   batching on CUDA), a pass only while ``--budget-s`` of wall time allows it (judged by the last pass of
   that way, else any): seconds per run and the features' agreement with plain next to plain's with plain again.

On a GPU (one H200/H100, ~5 minutes; a failure of a fused way is recorded and the other passes go on):

    python examples/anisompm/benchmarks/bench_fused.py --preset paper --runs 256 --batch 64 \\
        --ways plain fused fused_stored --budget-s 280 \\
        --out examples/anisompm/benchmarks/results/fused_substep_paper_h200.json

On the CPU (a check of the script; times mean little there): ``--preset tiny --arch cpu --runs 4 --batch 2
--frames 6``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm", ROOT / "benchmarks",
          Path(__file__).parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import emit, provenance, simulator_device  # noqa: E402
from bench_tiled_p2g import PAPER_SECONDS_PER_RUN, feature_agreement, perturbed_frame  # noqa: E402

#: the ways a substep can go: plain kernels, fused with g2p's state in registers (the default), fused with it
#: written back and read again (``fused_registers=False``: that lever alone)
WAYS = ("plain", "fused", "fused_stored")


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--arch", default="cuda", help="cpu: a check of the script (times mean little there)")
    p.add_argument("--runs", type=int, default=256)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--frames", type=int, default=None, help="override the preset's frames (shorter runs)")
    p.add_argument("--p2g", default="auto", choices=["auto", "atomic", "tiled"], help="taichi_p2g, every way")
    p.add_argument("--ways", nargs="+", default=["plain", "fused"], choices=WAYS,
                   help="compared with plain (always run first); each way's passes: once, then again")
    p.add_argument("--parity-steps", type=int, default=16)
    p.add_argument("--budget-s", type=float, default=270.0,
                   help="wall seconds for the whole script: a pass starts only if it should end within them")
    p.add_argument("--out", type=Path, default=None)
    return p.parse_args(argv)


def _save(out: dict, path: Path | None) -> None:
    """Write the result so far (``partial``): a device fault that ends the process keeps what was measured."""
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({**provenance(), **out, "partial": True}, indent=1) + "\n")


def _parity_state(sim, params: np.ndarray, steps: int) -> dict[str, np.ndarray]:
    """``steps`` substeps (dt 1e-4, grips still) of ``params``' runs from ``perturbed_state``: the particles."""
    backend = perturbed_frame(sim, params, steps)
    backend.advance(steps)
    backend.sync()
    x, d = backend.read()
    return {"x": x.astype(np.float64), "d": d.astype(np.float64)}


def _diff(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, float]:
    return {k: float(np.nanmax(np.abs(a[k] - b[k]))) for k in a}


def _kernel_profile(sim, B: int) -> dict[str, float]:
    """Seconds per launch of each substep stage (a throw-away state: frames of 8 substeps, see kernel_times)."""
    backend = sim.engine.backend(B)
    nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
    backend.set_frame(np.full(B, 1e-4), np.full(B, 8), np.zeros((B, 8, nk, 6)), damage_on=True)
    backend.kernel_times(3)   # compiled and warm
    times = backend.kernel_times(20)
    return {**times, "substep_total": float(sum(times.values()))}


def _features(results: list, ex) -> np.ndarray:
    nan = np.full(len(ex.feature_names), np.nan)
    return np.array([ex.extract(r.trajectory) if r.ok else nan for r in results])


def _run_passes(sims: dict, params: np.ndarray, ex, a, t_start: float, out: dict) -> dict[str, np.ndarray]:
    """Each way's pass, then each way's again, those that fit the budget; rows into ``out['passes']``, features
    returned."""
    feats: dict[str, np.ndarray] = {}
    last_wall: dict[str, float] = {}
    for name in [*sims, *(f"{w}_again" for w in sims)]:
        way = name.removesuffix("_again")
        if way not in sims:
            continue
        left = a.budget_s - (time.perf_counter() - t_start)
        guess = last_wall.get(way, max(last_wall.values(), default=0.0))   # this way's last pass, else any
        if guess > left or left <= 0:
            out["passes"][name] = {"skipped": f"a pass takes ~{guess:.1f} s, {left:.1f} s of the budget left"}
            continue
        try:
            if way not in last_wall:   # first use: the whole path compiled (untimed, two runs)
                sims[way].simulate(params[: min(2, len(params))])
            t0 = time.perf_counter()
            res = sims[way].simulate(params)
        except Exception as exc:   # the fused path failing on a device is a result too
            out["passes"][name] = {"error": f"{type(exc).__name__}: {exc}"[:2000]}
            sims.pop(way)
            continue
        wall = last_wall[way] = time.perf_counter() - t0
        feats[name] = _features(res, ex)
        out["passes"][name] = {"seconds_per_run": wall / len(params), "wall_s": wall,
                               "x_paper_156s": PAPER_SECONDS_PER_RUN * len(params) / wall,
                               "failed": int((~np.all(np.isfinite(feats[name]), axis=1)).sum())}
        print(name, f"{wall / len(params):.4f} s/run", flush=True)
        _save(out, a.out)
    return feats


def _agreement(feats: dict[str, np.ndarray], names: list[str]) -> dict:
    """Each way's features against plain's (first passes, and the again passes), and each way against itself."""
    pairs = {}
    for way in WAYS:
        pairs[f"{way}_vs_{way}_again"] = (way, f"{way}_again")
        if way != "plain":
            pairs[f"{way}_vs_plain"] = ("plain", way)
            pairs[f"{way}_again_vs_plain_again"] = ("plain_again", f"{way}_again")
    return {k: feature_agreement(feats[x], feats[y], names) for k, (x, y) in pairs.items()
            if x in feats and y in feats}


def _speedup(passes: dict) -> dict[str, float]:
    """Each way's speed-up over plain: mean seconds per run of plain's passes over the way's."""
    spr = {w: [r["seconds_per_run"] for n, r in passes.items()
               if n.removesuffix("_again") == w and "seconds_per_run" in r] for w in WAYS}
    return {w: float(np.mean(spr["plain"]) / np.mean(spr[w])) for w in WAYS
            if w != "plain" and spr[w] and spr["plain"]}


def _build(cfg: dict, ways: list[str], out: dict) -> dict:
    from invphys_orange_peel.simulator import OrangePeelSimulator

    class StoredSimulator(OrangePeelSimulator):
        """The fused substep with g2p's state written back and read again (``fused_registers=False``)."""

        def backend_options(self) -> dict:
            return {**super().backend_options(), "fused_registers": False}

    sims = {}
    for way in dict.fromkeys(["plain", *ways]):
        try:
            cls = StoredSimulator if way == "fused_stored" else OrangePeelSimulator
            sims[way] = cls(**cfg, taichi_fused=way != "plain")
        except Exception as exc:
            out["errors"][way] = f"{type(exc).__name__}: {exc}"
    return sims


def _device_checks(sims: dict, params: np.ndarray, a, out: dict) -> None:
    """State parity and the kernel profile, each way (an error of the fused path recorded, not raised)."""
    B = min(a.batch, len(params))
    states = {}
    for way in list(sims):
        try:
            out["errors"][way] = "started (a fault ended the process here)"
            _save(out, a.out)
            states[way] = _parity_state(sims[way], params[:B], a.parity_steps)
            if way == "plain":
                states["plain_again"] = _parity_state(sims[way], params[:B], a.parity_steps)
            out["kernel_seconds_per_launch"][way] = _kernel_profile(sims[way], B)
            del out["errors"][way]
        except Exception:
            out["errors"][way] = traceback.format_exc()[-3000:]
            sims.pop(way)
    if "plain" in states:
        scale = {k: float(np.nanmax(np.abs(v))) for k, v in states["plain"].items()}
        out["state_parity"] = {"scale": scale, "plain_vs_plain_again": _diff(states["plain"], states["plain_again"])}
        for way in states:
            if way not in ("plain", "plain_again"):
                out["state_parity"][f"{way}_vs_plain"] = _diff(states["plain"], states[way])
    kt = out["kernel_seconds_per_launch"]
    out["substep_kernel_speedup"] = {w: kt["plain"]["substep_total"] / kt[w]["substep_total"] for w in kt
                                     if w != "plain" and "plain" in kt}
    print("parity", out.get("state_parity"), "kernels", kt, flush=True)


def main(argv: list[str] | None = None) -> int:
    t_start = time.perf_counter()
    a = _args(argv)
    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.parameters import parameter_space

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.runs, space.dim)))
    cfg = {"backend": "taichi", "preset": a.preset, "arch": a.arch, "batch_size": a.batch, "taichi_p2g": a.p2g,
           **({"frames": a.frames} if a.frames else {})}
    out: dict = {"benchmark": "bench_fused", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
                 "preset": a.preset, "runs": a.runs, "batch": a.batch, "budget_s": a.budget_s, "errors": {},
                 "kernel_seconds_per_launch": {}, "passes": {}}
    sims = _build(cfg, a.ways, out)
    plain = sims["plain"]
    ident = RunIdentity.of(plain)
    backend = plain.engine.backend(min(a.batch, a.runs))
    out.update(simulator_version=ident.version, config_hash=ident.config, frames=plain.frames,
               scheduling=plain.config.scheduling, scatter=backend.p2g, g2p=backend.g2p,
               resort_every=backend.resort_every, device=simulator_device(plain))
    _device_checks(sims, params, a, out)
    ex = OrangePeelFeatures()
    feats = _run_passes(sims, params, ex, a, t_start, out)
    out["feature_agreement"] = _agreement(feats, ex.feature_names)
    out["runs_speedup_vs_plain"] = _speedup(out["passes"])
    out["wall_s"] = time.perf_counter() - t_start
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
