"""NPE in the box against NPE in logit space, without a simulator (issue 17): leakage, held-out log-prob
and the best-of-64 answers' parameter error on the 100 protocol targets.

The box posterior of `amortised_vs_lookup_paper_extra.yaml` (2,624 training rows) puts ~47 % of its draws
outside [0, 1]^9, which are clipped onto the box's faces; `transform: logit` cannot leak. This fits both on
the spec's training rows (its trained ensemble scores the draws) and reports, per variant: leakage, mean
log-prob of the 400 held-out rows' true theta, and for the 100 targets the answers' mean |theta - theta_true|
(normalised units) and R_surr. Simulated R_actual needs a GPU (add the variant to the spec's baselines).
usage: python results/orange_peel_paper_protocol_amortised/v030_extra/npe_transform.py RUN_DIR
   (RUN_DIR: an `invphys run ... amortised_vs_lookup_paper_extra.yaml --stage train --stage invert` output)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
SPEC = Path("examples/orange_peel/invphys_orange_peel/specs/amortised_vs_lookup_paper_extra.yaml")


def main() -> None:
    from invphys import registry
    from invphys.core.objectives import recovery_reward
    from invphys.core.spec import load_spec
    from invphys.pipeline.runner import StageContext

    run = Path(sys.argv[1])
    spec = load_spec(SPEC)
    ctx = StageContext(spec=spec, out=run, stage="validate", registry=registry.default_registry(), console=None,
                       progress=False)
    data, (tr, te) = ctx.dataset(), ctx.split()
    targets = json.loads((run / "invert" / "targets.json").read_text())
    feats, truth = np.asarray(targets["features"]), np.asarray(targets["theta"])
    scales, predict = ctx.scales(), ctx.surrogate().predict
    out = {"train_rows": len(tr), "held_out_rows": len(te), "targets": len(feats), "variants": {}}
    for transform in ("none", "logit"):
        npe = ctx.registry.create("optimizer", {"type": "npe", "samples": 64, "answer": "best_surrogate",
                                                "transform": transform})
        npe.fit(data.theta[tr], data.y[tr], scales)
        ans = npe.answer(feats, predict)
        leak = npe.last_leakage
        import torch

        x = torch.as_tensor(data.y[te], dtype=torch.float32)
        u = torch.as_tensor(npe._to_u(data.theta[te]), dtype=torch.float32)
        with torch.no_grad():
            lpt = npe._posterior.log_prob_batched(u[None], x=x, norm_posterior=False)[0].numpy().astype(np.float64)
        if transform == "logit":
            t = np.clip(data.theta[te], npe._EPS, 1 - npe._EPS)
            lpt = lpt - np.log(t * (1 - t)).sum(axis=1)
        r = np.array([recovery_reward(p, f, scales) for p, f in zip(predict(ans.theta), feats, strict=True)])
        out["variants"][transform] = {
            "leakage": round(leak, 4), "fit": {k: v for k, v in npe.metrics.items() if not isinstance(v, dict)},
            "held_out_mean_log_prob_of_truth": round(float(np.mean(lpt)), 3),
            "answers_mean_abs_error": round(float(np.mean(np.abs(ans.theta - truth))), 4),
            "answers_mean_abs_error_per_param": dict(zip(data.param_names, np.round(np.mean(np.abs(ans.theta - truth), 0), 4).tolist(), strict=True)),
            "answers_on_box_face": round(float(np.mean(np.any((ans.theta <= 0) | (ans.theta >= 1), axis=1))), 3),
            "answers_mean_R_surr": round(float(r.mean()), 4)}
        print(transform, json.dumps(out["variants"][transform]), flush=True)
    (HERE / "npe_transform.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
