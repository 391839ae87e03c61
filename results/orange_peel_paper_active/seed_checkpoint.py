"""Seed OUT/active/progress.npz from an active run made before the stage saved checkpoints.

Rounds 0-1 of results/orange_peel_paper_active ran before checkpointing existed: their records
(rounds.json), final answers (validation.json) and round 0's 200 runs (added.npz) were kept, round 1's
runs only where they became a target's best answer. This writes the checkpoint the stage would have
written, under the device spec's key, so `rounds: 3` resumes at round 2.
usage: python seed_checkpoint.py SPEC OUT
"""
import json
import sys
from pathlib import Path

import numpy as np

from invphys import registry
from invphys.core.spec import load_spec
from invphys.pipeline.context import StageContext
from invphys.pipeline.stages import active
from invphys.pipeline.stages.invert import load_results

spec_path, out = sys.argv[1], Path(sys.argv[2])
spec = load_spec(spec_path)
ctx = StageContext(spec=spec, out=out, stage="active", registry=registry.default_registry(), console=None,
                   progress=False)
_, targets = load_results(ctx)
n = min(spec.active.targets or int(spec.targets.validate_n) or len(targets["rows"]), len(targets["rows"]))
ks = list(range(n))
feats = np.asarray(targets["features"], dtype=np.float64)[ks]
d = out / "active"
rounds = json.loads((d / "rounds.json").read_text())
val = sorted(json.loads((d / "validation.json").read_text()), key=lambda r: r["target_index"])
added0 = np.load(d / "added.npz")
start = active._starts(ctx, spec.active.start, ks, targets)
best_theta = np.array([r["theta"] for r in val])
best_r = np.array([r["r_actual"] for r in val])
best_y = np.array([r["actual"] for r in val], dtype=np.float64)
seen0 = {tuple(np.round(t, 10)) for t in added0["theta"]}
from_round1 = np.array([tuple(np.round(t, 10)) not in seen0 and not np.allclose(t, s)
                        for t, s in zip(best_theta, start, strict=True)])
rounds[-1]["note"] = (f"runs kept: only the {int(from_round1.sum())} that became a target's best "
                      "(made before the stage saved checkpoints)")
key = active._checkpoint_key(ctx, n, feats)
active._save_checkpoint(ctx, key, rounds, (best_theta, best_r, best_y), [added0["theta"], best_theta[from_round1]],
                        [added0["y"], best_y[from_round1]])
print(f"seeded {d / active.CHECKPOINT_FILE}: {len(rounds)} rounds, round-1 rows kept {int(from_round1.sum())}, "
      f"best so far {best_r.mean():.4f}")
