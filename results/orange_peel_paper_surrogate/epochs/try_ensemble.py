"""One EnsembleSurrogate with JSON overrides on the bench split; prints held-out R^2 (used for epochs_check.json)."""
import json
import sys
import time

import numpy as np

sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[3]))
from invphys.models.data import r2_scores
from invphys.plugins.surrogates.ensemble import EnsembleSurrogate

d = np.load(sys.argv[3])  # tt, yt, tv, yv: the bench split
over = json.loads(sys.argv[1])
t0 = time.time()
m = EnsembleSurrogate(val_fraction=0.1, **over)
m.fit(d['tt'], d['yt'])
P = m._member_predict(d['tv'])
r, per = r2_scores(d['yv'], P.mean(0))
print(sys.argv[2], over, f"R2 {r:.4f} min {min(per):.3f}", ' '.join(f'{v:.3f}' for v in per), f"{time.time()-t0:.0f}s", flush=True)
