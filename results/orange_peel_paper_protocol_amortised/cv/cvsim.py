# ruff: noqa: E702
"""Hyper-parameter choice on TRAINING rows only, through the simulator (device).

Pseudo-targets: 32 farthest-point + 32 random training rows (scaled feature space). Each is answered
leave-one-out (the row itself excluded from the lookup) by the nearest neighbour and by local_linear
variants; every distinct answer is simulated and scored R_gt against the row's own features.
usage: python cvsim.py answers OUT.json   (CPU: answers only) | python cvsim.py simulate IN.json OUT.json
"""
import json
import os
import sys
import time

import numpy as np

from invphys.core.objectives import recovery_reward
from invphys.plugins.baselines.local_linear import LocalLinear

CONFIGS = {
    "ll_k15_t1": dict(k=15, ridge=0.3, kernel="gaussian", trust=1.0),
    "ll_k15_t2_a5": dict(k=15, ridge=0.3, kernel="gaussian", trust=2.0, anchors=5),
    "ll_k40_t2_a5": dict(k=40, ridge=0.1, kernel="gaussian", trust=2.0, anchors=5),
    "ll_k40_t4_a5": dict(k=40, ridge=0.1, kernel="gaussian", trust=4.0, anchors=5),
}
CS = {
    "cs_default": dict(k=40, ridge=0.1, kernel="gaussian"),
    "cs_small": dict(k=40, ridge=0.1, kernel="gaussian", trusts=[0.5, 1.0, 2.0], bandwidth=0.1),
}

def data():
    tr = np.load("runs/protocol_paper_lean/inverter/data/train.npz" if os.path.exists("runs/protocol_paper_lean") else ".gpu/h2b/train.npz")
    s = np.array(json.load(open("runs/protocol_paper_lean/invert/targets.json" if os.path.exists("runs/protocol_paper_lean") else ".gpu/h2b/targets.json"))["scales"])
    return tr["theta"], tr["y"], s

def pseudo_targets(Y, s, n_fp=32, n_rand=32, seed=1):
    z = Y / s
    rng = np.random.default_rng(seed)
    first = int(rng.integers(len(z)))
    chosen = [first]; d = np.linalg.norm(z - z[first], axis=1)
    while len(chosen) < n_fp:
        j = int(np.argmax(d)); chosen.append(j); d = np.minimum(d, np.linalg.norm(z - z[j], axis=1))
    rest = np.setdiff1d(np.arange(len(z)), chosen)
    return np.array(chosen), rng.choice(rest, n_rand, replace=False)

def answers():
    T, Y, s = data()
    fp, rnd = pseudo_targets(Y, s)
    rows = np.r_[fp, rnd]
    out = {"rows": rows.tolist(), "set": ["farthest_point"] * len(fp) + ["random"] * len(rnd), "answers": {}}
    for name, cfg in CONFIGS.items():
        p = LocalLinear(**cfg); p.fit(T, Y, s)
        t0 = time.perf_counter()
        th, _, pred, _ = p.answer_rows(Y[rows], exclude=rows)
        out["answers"][name] = {"theta": th.tolist(), "local_r": pred.tolist(),
                                "ms_per_target": 1e3 * (time.perf_counter() - t0) / len(rows)}
        if name == "ll_k15_t1":
            idx, _ = p.neighbours(Y[rows], exclude=rows)
            out["answers"]["nearest_neighbour"] = {"theta": T[idx[:, 0]].tolist(),
                                                   "dataset_r": recovery_reward(Y[idx[:, 0]], Y[rows], s).tolist()}
    from invphys.plugins.baselines.corrected_search import CorrectedSearch
    from invphys.registry import default_registry
    ens = default_registry().get("surrogate", "ensemble").load("runs/protocol_paper_lean/train/surrogate")
    keep = np.ones(len(T), bool)
    for name, cfg in CS.items():
        th, pr, t0 = [], [], time.perf_counter()
        for q in rows:
            keep[:] = True; keep[q] = False
            p = CorrectedSearch(**cfg); p.fit(T[keep], Y[keep], s)
            a = p.answer(Y[q:q + 1], ens.predict); th.append(a.theta[0]); pr.append(a.info["corrected_r"][0])
        out["answers"][name] = {"theta": np.array(th).tolist(), "local_r": pr,
                                "ms_per_target": 1e3 * (time.perf_counter() - t0) / len(rows)}
    for k, v in out["answers"].items():
        print(k, "local/dataset R {:.3f}".format(np.mean(v.get("local_r", v.get("dataset_r")))), "ms {:.2f}".format(v.get("ms_per_target", 0)))
    return out

def simulate(blob, dst):
    from invphys_orange_peel.features import OrangePeelFeatures
    from invphys_orange_peel.simulator import OrangePeelSimulator

    from invphys.plugins.validators.simulator import SimulatorValidator
    _T, Y, s = data(); rows = np.array(blob["rows"])
    sim = OrangePeelSimulator(OrangePeelSimulator.Config(preset=os.environ.get("H2_PRESET", "paper"), backend="taichi", arch=os.environ.get("H2_ARCH", "cuda"), batch_size=256))
    ext = OrangePeelFeatures(); val = SimulatorValidator(SimulatorValidator.Config(batch_size=128))
    names = list(blob["answers"])
    allth = np.concatenate([np.array(blob["answers"][n]["theta"]) for n in names])
    uniq, inv = np.unique(np.round(allth, 10), axis=0, return_inverse=True)
    print("distinct answers", len(uniq), "of", len(allth), flush=True)
    feats = np.full((len(uniq), Y.shape[1]), np.nan); t0 = time.time()
    for a in range(0, len(uniq), 128):
        feats[a:a + 128] = val.simulate_features(uniq[a:a + 128], sim, ext).features
        print(f"simulated {min(a + 128, len(uniq))}/{len(uniq)} in {time.time() - t0:.0f} s", flush=True)
        res = {"rows": blob["rows"], "set": blob["set"], "r_actual": {}}
        f_all = feats[inv.reshape(-1)].reshape(len(names), len(rows), -1)
        for i, n in enumerate(names):
            r = recovery_reward(f_all[i], Y[rows], s)
            res["r_actual"][n] = [None if not np.isfinite(x) or np.isnan(f_all[i][j]).any() else float(x) for j, x in enumerate(r)]
        json.dump(res, open(dst, "w"))
    sets = np.array(blob["set"])
    for n in names:
        r = np.array([np.nan if x is None else x for x in res["r_actual"][n]])
        print(f"{n:20s} R_actual {np.nanmean(r):.3f} fp {np.nanmean(r[sets == 'farthest_point']):.3f} rand {np.nanmean(r[sets == 'random']):.3f} n {np.isfinite(r).sum()}")

if __name__ == "__main__":
    if sys.argv[1] == "answers":
        json.dump(answers(), open(sys.argv[2], "w"))
    else:
        simulate(json.load(open(sys.argv[2])), sys.argv[3])
