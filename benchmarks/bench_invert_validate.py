"""``invphys invert --validate`` against the pipeline's validate path, on the same parameters.

    python benchmarks/bench_invert_validate.py --bundle inverters/orange_peel_paper \
        --targets benchmarks/data/invert_validate_paper_targets.json \
        --out benchmarks/results/invert_validate_paper_cuda.json

1. runs ``invphys invert BUNDLE --target TARGETS --validate --json`` in a fresh process (what a user runs);
2. re-simulates the returned parameters the way the ``validate`` stage of ``invphys run`` does (the
   ``simulator`` validator's ``simulate_features`` on the bundle's recorded simulator config, in one
   batch), together with the targets' true parameters (``theta_true``: the noise floor, and a check
   that the simulator reproduces the dataset rows);
3. records both R_actual per target and their largest difference.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path


def _device() -> str:
    try:
        import torch

        if torch.cuda.is_available():
            return f"cuda:{torch.cuda.get_device_name(0)}"
    except ImportError:
        pass
    return "cpu"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", default="inverters/orange_peel_paper")
    ap.add_argument("--targets", required=True, help="target file with 'targets' and 'theta_true'")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()

    import numpy as np

    import invphys
    from invphys.core.masked_recovery import masked_recovery

    t0 = time.perf_counter()
    cli = subprocess.run([sys.executable, "-m", "invphys.cli", "invert", args.bundle, "--target", args.targets,
                          "--validate", "--json"], capture_output=True, text=True)
    cli_s = time.perf_counter() - t0
    if cli.returncode:
        raise SystemExit(f"invphys invert failed ({cli.returncode}):\n{cli.stderr[-3000:]}")
    answer = json.loads(cli.stdout)
    spec = json.loads(Path(args.targets).read_text())

    inv = invphys.load_inverter(args.bundle)
    names = inv.parameter_names
    theta = np.array([inv.parameter_space.normalize(np.array(
        [r["candidates"][0]["parameters"][n]["value"] for n in names])) for r in answer["results"]])
    truth = np.asarray(spec["theta_true"], dtype=np.float64)
    goals = np.array([[r["candidates"][0]["features"][f]["target"] for f in inv.feature_names]
                      for r in answer["results"]])
    sim = inv.simulator()
    ext = inv.extractor(sim)
    m = inv.bundle.manifest
    batch = int(m["simulator"]["config"].get("batch_size", 64))
    validator = inv.bundle.registry.create("validator", {"type": "simulator", "batch_size": batch})
    t1 = time.perf_counter()
    out = validator.simulate_features(np.concatenate([theta, truth]), sim, ext)
    stage_s = time.perf_counter() - t1
    n = len(theta)
    r_stage = masked_recovery(out.features[:n], goals, inv.bundle.scales, kappa=inv.bundle.kappa)
    r_truth = masked_recovery(out.features[n:], goals, inv.bundle.scales, kappa=inv.bundle.kappa)
    rows = []
    for i, r in enumerate(answer["results"]):
        c = r["candidates"][0]
        rows.append({"target": r["target"], "r_surrogate": c["r_surrogate"], "r_actual_invert_cli": c["r_actual"],
                     "r_actual_validate_path": float(r_stage[i]), "gap": c["gap"],
                     "r_true_parameters": float(r_truth[i]), "failure": out.failures[i],
                     "parameters": {k: v["value"] for k, v in c["parameters"].items()}})
    diffs = [abs(x["r_actual_invert_cli"] - x["r_actual_validate_path"]) for x in rows
             if x["r_actual_invert_cli"] is not None]
    result = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "invert_command": f"invphys invert {args.bundle} --target {args.targets} --validate --json",
        "bundle": args.bundle, "bundle_id": m.get("bundle_id"), "method": answer["method"],
        "simulator": f"{m['simulator']['name']} {m['simulator']['version']}", "simulator_config": m["simulator"]["config"],
        "targets": len(rows), "targets_file": args.targets,
        "max_abs_diff_r_actual": max(diffs) if diffs else None,
        "mean_r_surrogate": float(np.mean([x["r_surrogate"] for x in rows])),
        "mean_r_actual": float(np.nanmean([x["r_actual_validate_path"] for x in rows])),
        "mean_r_true_parameters": float(np.nanmean(r_truth)),
        "invert_cli_wall_s": round(cli_s, 2), "validate_path_wall_s": round(stage_s, 2),
        "validate_path_runs": int(len(theta) + len(truth)), "validate_path_batch_size": batch,
        "rows": rows,
        "device": {"accelerator": _device(), "python": platform.python_version(), "numpy": np.__version__},
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "rows"}, indent=2))


if __name__ == "__main__":
    main()
