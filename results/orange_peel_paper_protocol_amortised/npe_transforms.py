"""Does a feature or parameter transform help sbi's NPE at 9,600 training rows? (stop 33, not validated)

Fits the `npe` baseline on the 10k spec's training rows, once per variant, and scores its 64 draws on the 400
held-out rows of datasets/orange_peel_paper: mean |theta - theta_true| of the best draw by log-prob, of the
draws' mean, and of the best draw by the run's trained ensemble (R on the features / s_k), plus the fraction
of draws outside [0, 1]^9. The trained ensemble is read from RUN/train (make RUN with the spec's train stage).
usage: python results/orange_peel_paper_protocol_amortised/npe_transforms.py SPEC RUN {default,robust} ['{"transform": "logit"}']
  prints one JSON line; npe_transforms.jsonl holds the lines of stop 33 (2-core CPU, ~2.5 min per fit)
"""
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from invphys.core.spec import load_spec
from invphys.pipeline.context import StageContext
from invphys.plugins.baselines.npe import NPEBaseline
from invphys.registry import default_registry


def main(spec_path: str, run: str, variant: str, options: str = "{}") -> dict:
    reg = default_registry()
    ctx = StageContext(spec=load_spec(spec_path, reg), out=Path(run), stage="report", registry=reg, progress=False)
    data = ctx.dataset()
    tr, te = ctx.split()
    sc = ctx.scales()
    th, y = data.theta, data.y
    med = np.median(y[tr], 0)
    iqr = np.percentile(y[tr], 75, 0) - np.percentile(y[tr], 25, 0)

    def tf(v: np.ndarray) -> np.ndarray:
        return np.arcsinh((v - med) / (iqr / 1.349)) if variant == "robust" else v

    cfg = json.loads(options)
    p = NPEBaseline(NPEBaseline.Config(samples=64, answer="best_log_prob", **cfg))
    t0 = time.time()
    info = p.fit(th[tr], tf(y[tr]), sc)
    fit_s = time.time() - t0
    x = torch.as_tensor(tf(y[te]), dtype=torch.float32)
    with torch.no_grad():
        lp = p._posterior.log_prob_batched(torch.as_tensor(th[te], dtype=torch.float32)[None], x=x,
                                           norm_posterior=False).numpy()[0]
    s, logp = p.posterior_samples(tf(y[te]))
    rows = np.arange(len(te))
    best, mean = s[rows, logp.argmax(1)], s.mean(1)
    pred = ctx.surrogate().predict(s.reshape(-1, s.shape[2])).reshape(s.shape[0], s.shape[1], -1)
    r = 1 - np.mean(np.abs((pred - y[te][:, None, :]) / sc), axis=2)
    by_surrogate = s[rows, r.argmax(1)]
    return dict(variant=variant, cfg=cfg, fit_s=round(fit_s, 1), **info,
                heldout_logq_true=float(np.mean(lp)), median_logq=float(np.median(lp)),  # in the flow's space
                err_best_logprob=float(np.mean(np.abs(best - th[te]))), err_mean=float(np.mean(np.abs(mean - th[te]))),
                err_best_surrogate=float(np.mean(np.abs(by_surrogate - th[te]))), leakage=p.last_leakage)


if __name__ == "__main__":
    print(json.dumps(main(*sys.argv[1:5])), flush=True)
