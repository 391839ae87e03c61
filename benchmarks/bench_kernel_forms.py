"""Kernel forms of the orange peel's Taichi substep on a GPU: per-stage time, whole runs, agreement.

Nsight Compute found ``g2p`` at 12 % occupancy (215 registers per thread, its 27 nodes unrolled). The
``loop`` form (``taichi_g2p: loop``, CUDA's default) does the same sums with loops over two of the three
axes: 117 registers (``docs/gpu-throughput.md``). ``benchmarks/results/kernel_forms_paper_h100.json``
also measured a split P2G (stress terms stored by one kernel, scattered by the next; forms
``split:...``), slower, removed after commit de20e72; its forms there are named ``p2g:g2p``.

On ``--runs`` random parameter vectors (seed 0) of ``--preset``, in lock-step batches of ``--batch``:

1. **g2p parity**: every form's g2p on the same grid and particle state (``perturbed_state``), against the
   first form: the largest difference per particle array (0.0: bit for bit);
2. **kernel times**: seconds per launch of each substep stage (``kernel_times``, synchronised) for every
   g2p form in ``--forms``, and the substep's total against the first form; and the substep when
   ``--steps`` of them are launched back to back with one sync at the end (launch gaps hidden);
3. **whole runs**: the first form, the fastest other form, then both again (alternating, since one
   machine's whole-run times drift by several per cent; GPU float atomics make two passes of the same
   form differ: that spread is the yardstick): seconds per run, the ratio to the paper's 156 s, and the
   features' agreement with the first pass.

    python benchmarks/bench_kernel_forms.py --preset paper --runs 128 --batch 64 --out $OUT/kernel_forms.json

The CPU test ``tests/test_taichi_tiled_p2g.py`` checks that the forms agree to float rounding.
"""

from __future__ import annotations

import argparse
import datetime as dt
import shlex
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "examples" / "orange_peel", ROOT / "examples" / "anisompm", Path(__file__).parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from _machine import emit  # noqa: E402
from bench_tiled_p2g import PAPER_SECONDS_PER_RUN, feature_agreement, set_perturbed_state, timed_features  # noqa: E402

G2P_FORMS = ("unrolled", "loop")
PARTICLE_ARRAYS = ("x", "v", "C", "F", "d")


def _args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--runs", type=int, default=128)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--arch", default="cuda", help="cpu: a check of the script (times mean nothing there)")
    p.add_argument("--p2g", default="auto", choices=["auto", "atomic", "tiled"], help="the scatter")
    p.add_argument("--forms", default="unrolled,loop", help="comma-separated g2p forms; the first is the baseline")
    p.add_argument("--steps", type=int, default=20, help="synchronised substeps timed per form")
    p.add_argument("--frames", type=int, default=None, help="override the preset's frames (shorter runs)")
    p.add_argument("--skip-runs", action="store_true", help="kernel times only")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    a.forms = a.forms.split(",")
    for f in a.forms:
        if f not in G2P_FORMS:
            p.error(f"a form is one of {list(G2P_FORMS)}, got {f!r}")
    return a


def _loaded(sim, params: np.ndarray, substeps: int):
    """``sim``'s backend with ``params`` loaded and a frame of ``substeps`` active substeps set (a fresh
    backend has none: its kernels would skip every particle)."""
    from invphys_orange_peel.engine_scene import model_for

    B = len(params)
    backend = sim.engine.backend(B)
    model = model_for(sim.engine_scene, params)
    backend.load(model.table(), model.friction)
    nk = max(len(sim.engine_scene.engine.kinematic_names), 1)
    backend.set_frame(np.full(B, 1e-4), np.full(B, substeps), np.zeros((B, 1, nk, 6)), damage_on=True)
    return backend


def g2p_parity(sim, params: np.ndarray, forms: list[str]) -> dict[str, dict[str, float]]:
    """Every g2p form in ``forms`` on one grid: the runs set to ``perturbed_state``, one clear, P2G and grid
    update, then each form's g2p from the same particle state; the largest difference of each particle array
    from the first form's, over its largest value (0.0: bit for bit)."""
    from invphys_anisompm.backends.taichi_backend import _STAGE_ARGS, _build_g2p, _kernels

    backend = _loaded(sim, params, 2)
    set_perturbed_state(backend)
    stages = backend._stages(0)
    for stage in ("clear", "p2g", "grid"):
        stages[stage]()
    before = {n: backend.particle_array(n) for n in PARTICLE_ARRAYS}
    after: dict[str, dict[str, np.ndarray]] = {}
    for form in forms:
        for n, values in before.items():
            backend.set_particle_array(n, values)
        _kernels(_build_g2p, form == "unrolled", backend.component_major)(*(backend._stage_value(n, 0) for n in _STAGE_ARGS["g2p"]))
        backend.sync()
        after[form] = {n: backend.particle_array(n).astype(np.float64) for n in PARTICLE_ARRAYS}
    ref = after[forms[0]]
    return {form: {n: float(np.abs(after[form][n] - ref[n]).max() / (np.abs(ref[n]).max() or 1.0))
                   for n in PARTICLE_ARRAYS} for form in forms[1:]}


def _streamed_substep(sim, params: np.ndarray, steps: int) -> float:
    """Seconds per substep of ``steps`` substeps launched back to back (one sync at the end), every run
    active: the GPU's substep with launch gaps hidden, against the sum of the synchronised stage times."""
    import time

    backend = _loaded(sim, params, steps)
    backend.advance(steps)   # warm: compiles whatever advance(steps) launches (Taichi graphs of substeps)
    backend.sync()
    t0 = time.perf_counter()
    backend.advance(steps)
    backend.sync()
    return (time.perf_counter() - t0) / steps


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.parameters import parameter_space
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.core.dataset import RunIdentity

    space = parameter_space()
    params = space.denormalize(np.random.default_rng(0).uniform(size=(a.runs, space.dim)))
    cfg = {"backend": "taichi", "preset": a.preset, "arch": a.arch, "batch_size": a.batch, "taichi_p2g": a.p2g}
    if a.frames:
        cfg["frames"] = a.frames
    sims = {g2p: OrangePeelSimulator(**cfg, taichi_g2p=g2p) for g2p in a.forms}
    names = list(sims)
    base = sims[names[0]]
    ident = RunIdentity.of(base)
    out: dict = {"benchmark": "bench_kernel_forms", "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
                 "command": "python " + " ".join(shlex.quote(x) for x in [sys.argv[0], *(argv or sys.argv[1:])]),
                 "simulator_version": ident.version, "config_hash": ident.config, "preset": a.preset,
                 "runs": a.runs, "batch": a.batch, "frames": base.frames,
                 "scatter": base.engine.backend(a.batch).p2g, "device": base.engine.backend(a.batch).device}

    if len(names) > 1:
        out["g2p_parity_vs_first"] = g2p_parity(base, params[:a.batch], names)
        print("g2p parity against", names[0], out["g2p_parity_vs_first"], flush=True)

    times: dict[str, dict[str, float]] = {}
    streamed: dict[str, float] = {}
    for name, sim in sims.items():
        backend = _loaded(sim, params[:a.batch], a.steps + 3)
        backend.kernel_times(3)   # compile and warm
        times[name] = backend.kernel_times(a.steps)
        print(name, {k: f"{v * 1e3:.3f} ms" for k, v in times[name].items()}, flush=True)
        streamed[name] = _streamed_substep(sim, params[:a.batch], a.steps)
        print(name, f"streamed substep {streamed[name] * 1e3:.3f} ms", flush=True)
    total = {n: sum(t.values()) for n, t in times.items()}
    out["kernel_seconds_per_substep"] = times
    out["substep_seconds"] = total
    out["substep_seconds_streamed"] = streamed
    out["substep_speedup_vs_first"] = {n: total[names[0]] / total[n] for n in names}
    print("substep speed-up against", names[0], out["substep_speedup_vs_first"], flush=True)

    if not a.skip_runs and len(names) > 1:
        best = min(names[1:], key=total.__getitem__)
        ex = OrangePeelFeatures()
        feats, walls = {}, {}
        passes = (("first", names[0]), ("best", best), ("first_again", names[0]), ("best_again", best))
        for label, name in passes:
            walls[label], feats[label] = timed_features(sims[name], params, ex)
            print(label, name, f"{walls[label] / a.runs:.3f} s/run", flush=True)
        out["runs_forms"] = {"first": names[0], "best": best}
        form_of = dict(passes)
        out["runs_result"] = {
            label: {"form": form_of[label], "seconds_per_run": walls[label] / a.runs,
                    "speedup_vs_paper_156s": PAPER_SECONDS_PER_RUN * a.runs / walls[label],
                    "failed": int((~np.all(np.isfinite(feats[label]), axis=1)).sum())} for label in walls}
        out["runs_speedup_best_vs_first"] = (walls["first"] + walls["first_again"]) / (walls["best"] + walls["best_again"])
        out["feature_agreement"] = {
            "best_vs_first": feature_agreement(feats["first"], feats["best"], ex.feature_names),
            "first_vs_first_again": feature_agreement(feats["first"], feats["first_again"], ex.feature_names),
            "best_vs_best_again": feature_agreement(feats["best"], feats["best_again"], ex.feature_names)}
    emit(out, a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
