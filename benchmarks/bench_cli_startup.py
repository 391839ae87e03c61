"""How long `invphys plugins` takes, and which heavy libraries it imports (it must import none); and how long
a one-target `invphys invert` of the all-data paper bundle takes from a fresh process, and which of the
libraries it needs no longer imports (sbi, scikit-learn, scipy.stats).

    python benchmarks/bench_cli_startup.py [--repeat 5] [--out benchmarks/results/cli_startup.json]

Runs the real console script in fresh processes (wall time, median of --repeat), then re-runs each
command in-process to list the heavy modules that got imported.
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
#: what a one-target answer of a saved bundle must not import (its flows are rebuilt without sbi)
ANSWER_AVOIDS = ("sbi", "sklearn", "scipy.stats", "taichi", "warp", "stable_baselines3", "ray")
BUNDLE = "inverters/orange_peel_paper_all"
#: the target: the features of the first row (lowest sample index) of this fresh uniform store
TARGETS = "datasets/orange_peel_paper_fresh_uniform"


def _timed(cmd: list[str], repeat: int) -> list[float]:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return times


def _imported(argv: list[str], watch: tuple[str, ...]) -> tuple[list[str], str]:
    """The modules of ``watch`` that running the CLI with ``argv`` in one process imports, and its stdout."""
    probe = ("import sys; from invphys.cli import app\n"
             f"try:\n    app({argv!r})\nexcept SystemExit:\n    pass\n"
             f"print('HEAVY=' + ','.join(m for m in {watch!r} if m in sys.modules), file=sys.stderr)")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    heavy = next(line for line in proc.stderr.splitlines() if line.startswith("HEAVY=")).split("=", 1)[1]
    return [m for m in heavy.split(",") if m], proc.stdout


def _first_target() -> list[str]:
    """``--feature NAME=VALUE`` arguments of the first row of :data:`TARGETS`."""
    import pyarrow.parquet as pq

    table = pq.read_table(sorted(Path(TARGETS).glob("part-*.parquet"))).to_pandas()
    row = table.sort_values("sample_index").iloc[0]
    pairs = [f"{c[2:]}={float(row[c])!r}" for c in table.columns if c.startswith("f_")]
    return [a for pair in pairs for a in ("--feature", pair)]


def _invert_one(exe: str, repeat: int) -> dict:
    argv = ["invert", BUNDLE, *_first_target(), "--json"]
    times = _timed([exe, *argv], repeat)
    heavy, out = _imported(argv, ANSWER_AVOIDS)
    return {"command": f"invphys invert {BUNDLE} --feature ... (12 features of {TARGETS}'s first row) --json", "median_s": round(statistics.median(times), 3),
            "max_s": round(max(times), 3), "runs": [round(t, 3) for t in times],
            "avoided_modules_imported": heavy, "answered": bool(out.strip())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "cli_startup.json")
    args = ap.parse_args()
    exe = shutil.which("invphys") or str(Path(sys.executable).parent / "invphys")
    times = _timed([exe, "plugins", "--json"], args.repeat)
    heavy, out = _imported(["plugins", "--json"], HEAVY)
    result = {
        "command": "invphys plugins --json",
        "median_s": round(statistics.median(times), 3),
        "max_s": round(max(times), 3),
        "runs": [round(t, 3) for t in times],
        "plugins_listed": len(json.loads(out)),
        "heavy_modules_imported": heavy,
        "limit_s": 1.5,
        "invert_one_target": _invert_one(exe, args.repeat),
        "machine": f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
