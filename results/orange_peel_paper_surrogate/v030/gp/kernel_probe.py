"""Split 0 only: does a rougher kernel rescue the GP on its two weakest features? (follow-up to gp_study.py)

    python results/orange_peel_paper_surrogate/v030/gp/kernel_probe.py    # writes kernel_probe.json

Same rows as the benchmark's split 0; one GP per feature on the standardised feature, ARD over the 9
parameters, white noise, no restarts. Kernel: Matern nu=1.5 (gp_study.py used nu=2.5).
"""

from __future__ import annotations

import json
import time

import numpy as np
from gp_study import HERE, load_split

FEATURES = ["interior_dispersion", "skin_detachment_fraction"]


def fit(x, z, xt, nu):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

    kernel = (ConstantKernel(1.0, (1e-2, 1e2)) * Matern(np.full(x.shape[1], 0.5), (1e-2, 1e3), nu=nu)
              + WhiteKernel(1e-2, (1e-5, 1.0)))
    t = time.time()
    gp = GaussianProcessRegressor(kernel, n_restarts_optimizer=0, random_state=0).fit(x, z)
    return gp.predict(xt), str(gp.kernel_), time.time() - t


def main() -> None:
    from joblib import Parallel, delayed

    from invphys.models.data import r2_scores

    names, x, y, xt, yt = load_split(0)
    jobs = [(f, nu) for nu in (1.5,) for f in FEATURES]
    cols = [names.index(f) for f, _ in jobs]
    res = Parallel(n_jobs=1)(delayed(fit)(x, (y[:, j] - y[:, j].mean()) / y[:, j].std(), xt, nu)
                             for j, (_, nu) in zip(cols, jobs, strict=True))
    out = {}
    for (f, nu), j, (p, k, t) in zip(jobs, cols, res, strict=True):
        pred = p * y[:, j].std() + y[:, j].mean()
        r2 = r2_scores(yt[:, [j]], pred[:, None])[0]
        out.setdefault(f"matern_nu{nu}", {})[f] = {"r2": r2, "kernel": k, "time_s": t}
        print(f"nu={nu} {f}: R^2 {r2:.3f} ({t:.0f} s) {k}", flush=True)
    (HERE / "kernel_probe.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
