"""How long `invphys plugins` takes, and which heavy libraries it imports (it must import none).

    python benchmarks/bench_cli_startup.py [--repeat 5] [--out benchmarks/results/cli_startup.json]

Runs the real console script in fresh processes (wall time, median of --repeat), then re-runs the
command in-process under ``-X importtime`` to list any heavy module that got imported.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HEAVY = ("torch", "taichi", "warp", "stable_baselines3", "ray", "cma", "nevergrad", "gymnasium")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "cli_startup.json")
    args = ap.parse_args()
    exe = shutil.which("invphys") or str(Path(sys.executable).parent / "invphys")
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        subprocess.run([exe, "plugins", "--json"], check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    probe = ("import sys; from invphys.cli import app\n"
             "try:\n    app(['plugins', '--json'])\nexcept SystemExit:\n    pass\n"
             f"print('HEAVY=' + ','.join(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    heavy = next(line for line in proc.stderr.splitlines() if line.startswith("HEAVY=")).split("=", 1)[1]
    n_plugins = len(json.loads(proc.stdout))
    result = {
        "command": "invphys plugins --json",
        "median_s": round(statistics.median(times), 3),
        "max_s": round(max(times), 3),
        "runs": [round(t, 3) for t in times],
        "plugins_listed": n_plugins,
        "heavy_modules_imported": [m for m in heavy.split(",") if m],
        "limit_s": 1.5,
        "machine": f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
