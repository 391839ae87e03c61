"""GPU re-run noise of simulator 0.3.0 (issue 11's done-when), read from this run's committed validation.

    .venv/bin/python results/orange_peel_paper_protocol_v030/noise_floor.py

The protocol's ``noise_floor`` method answers each of the 100 held-out targets with its own true parameters;
the validate stage re-simulated them (on the GPU named in ``validate/simulated.jsonl``) and scored the runs
against the stored features with R_gt = exp(-3 rms_k((y_k - y*_k) / s_k)), as
``benchmarks/bench_simulator_noise.py`` does. Writes ``noise_floor.json`` next to this file.
"""

from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent


def main() -> dict:
    with tarfile.open(HERE / "validate.tgz") as tar:
        rows = pd.read_csv(io.BytesIO(tar.extractfile("validate/validation.csv").read()))
        runs = [json.loads(line) for line in tar.extractfile("validate/simulated.jsonl").read().decode().splitlines()
                if line.strip()]
    r = rows.loc[rows["optimizer"] == "noise_floor", "r_actual"].to_numpy(dtype=float)
    devices = sorted({run["stats"]["device"] for run in runs if run.get("stats", {}).get("device")})
    out = {"source": "results/orange_peel_paper_protocol_v030/validate.tgz", "simulator": "orange_peel 0.3.0, paper preset",
           "stored_features": "datasets/orange_peel_paper (generated on one NVIDIA H100)", "rerun_devices": devices,
           "rows": len(r), "r_gt": {"median": float(np.median(r)), "mean": float(r.mean()), "min": float(r.min()),
                                          "p10": float(np.percentile(r, 10)), "below_0.95": int((r < 0.95).sum()),
                                          "at_least_0.995": int((r >= 0.995).sum())}}
    (HERE / "noise_floor.json").write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
