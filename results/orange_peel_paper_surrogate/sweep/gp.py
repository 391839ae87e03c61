"""Peers: GP (ARD Matern 2.5 + white noise, per feature, outputs standardised after Yeo-Johnson) and
histogram gradient boosting, on the same split; R^2 in raw units."""
import json, sys, time
import numpy as np
from joblib import Parallel, delayed
sys.argv = [sys.argv[0], sys.argv[1], sys.argv[2]] + sys.argv[3:]
import sweep
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel
from sklearn.ensemble import HistGradientBoostingRegressor

OUT = sys.argv[2]
TT, YT, TV, YV = sweep.TT, sweep.YT, sweep.TV, sweep.YV


def gp_feature(j, kind):
    tf = sweep.Transform(kind, YT)
    t = tf.fwd(YT)[:, j]
    k = ConstantKernel(1.0, (1e-2, 1e2)) * Matern(length_scale=np.ones(TT.shape[1]), length_scale_bounds=(1e-2, 1e3), nu=2.5) \
        + WhiteKernel(1e-3, (1e-8, 1e0))
    g = GaussianProcessRegressor(k, normalize_y=False, n_restarts_optimizer=0, random_state=0).fit(TT, t)
    full = np.zeros((len(TV), YT.shape[1]))
    full[:, j] = g.predict(TV)
    return tf.inv(full)[:, j], str(g.kernel_)


def gbm_feature(j, kind):
    tf = sweep.Transform(kind, YT)
    t = tf.fwd(YT)[:, j]
    g = HistGradientBoostingRegressor(max_iter=2000, learning_rate=0.03, max_leaf_nodes=15, min_samples_leaf=10,
                                      l2_regularization=1e-3, early_stopping=True, validation_fraction=0.1,
                                      n_iter_no_change=50, random_state=0).fit(TT, t)
    full = np.zeros((len(TV), YT.shape[1]))
    full[:, j] = g.predict(TV)
    return tf.inv(full)[:, j], int(g.n_iter_)


res = {}
for label, fn, kind in (("gbm_yj", gbm_feature, "yj"), ("gp_yj", gp_feature, "yj"), ("gp_none", gp_feature, "none")):
    t0 = time.time()
    outs = Parallel(n_jobs=12)(delayed(fn)(j, kind) for j in range(YT.shape[1]))
    P = np.stack([o[0] for o in outs], 1)
    r, per = sweep.r2(YV, P)
    res[label] = {"r2": r, "per_feature": per, "info": [o[1] for o in outs], "time_s": time.time() - t0}
    np.savez_compressed(f"{OUT}/pred_{label}.npz", P=P.astype(np.float32))
    print(label, round(r, 4), np.round(per, 3).tolist(), f"{time.time() - t0:.0f}s", flush=True)
    json.dump(res, open(f"{OUT}/peers.json", "w"))
