"""Where a GPU waits: busy time and idle gaps from an Nsight Systems kernel trace (issue 16).

``nsys profile -t cuda`` records every kernel and every CUDA API call of a process; ``nsys stats -r
cuda_gpu_trace,cuda_api_trace --format csv`` writes them as CSV. This script reads the two and reports, over the
window from the first to the last kernel (or ``--last-s`` seconds of it that end ``--skip-last-s`` before
the last kernel: a dataset's steady state, without its compilation, warm-up and final drain): the share of time some kernel
ran, the idle gaps between kernels (count, total, by size), and the gaps that follow a synchronising
device-to-host copy (a stream's frame end or particle read): the host's work between a sync and the next launch.

    nsys profile -t cuda --sample=none --cpuctxsw=none -o trace python3 benchmarks/bench_dataset.py ...
    nsys stats -r cuda_gpu_trace,cuda_api_trace --format csv -o trace trace.nsys-rep
    python3 examples/anisompm/benchmarks/gpu_timeline_gaps.py trace_cuda_gpu_trace.csv trace_cuda_api_trace.csv --last-s 30 \
        --skip-last-s 12 --out gaps.json
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import sys
from pathlib import Path

import numpy as np


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _col(rows: list[dict[str, str]], *names: str) -> np.ndarray:
    for n in names:
        if rows and n in rows[0]:
            return np.array([float(r[n] or 0) for r in rows])
    raise SystemExit(f"error: none of the columns {names} in the trace (columns: {list(rows[0]) if rows else []})")


def gaps_report(gpu_csv: Path, api_csv: Path | None, last_s: float | None = None, skip_last_s: float = 0.0) -> dict:
    """Busy share, idle gaps and the gaps after synchronising copies of a kernel trace (times in ns)."""
    rows = [r for r in _rows(gpu_csv) if "memcpy" not in r.get("Name", "").lower()
            and "memset" not in r.get("Name", "").lower()]
    start = _col(rows, "Start (ns)", "Start")
    end = start + _col(rows, "Duration (ns)", "Duration")
    order = np.argsort(start)
    start, end = start[order], end[order]
    if last_s is not None:
        stop = end.max() - skip_last_s * 1e9
        keep = (start >= stop - last_s * 1e9) & (end <= stop)
        start, end = start[keep], end[keep]
    reach = np.maximum.accumulate(end)        # kernels may overlap: the busy front so far
    gap = np.maximum(start[1:] - reach[:-1], 0.0)
    span = end.max() - start.min()
    busy = span - gap.sum()
    edges_us = [0, 5, 20, 100, 1000, 5000, 20000, np.inf]
    hist = {f"{lo}-{hi} us": {"count": int(((gap >= lo * 1e3) & (gap < hi * 1e3)).sum()),
                               "total_s": float(gap[(gap >= lo * 1e3) & (gap < hi * 1e3)].sum() / 1e9)}
            for lo, hi in itertools.pairwise(edges_us)}
    out = {"kernels": len(start), "window_s": float(span / 1e9), "busy_s": float(busy / 1e9),
           "busy_share": float(busy / span), "idle_s": float(gap.sum() / 1e9), "gaps_by_size": hist}
    if api_csv is not None:
        api = _rows(api_csv)
        names = [r.get("Name", "") for r in api]
        a_start = _col(api, "Start (ns)", "Start")
        a_end = a_start + _col(api, "Duration (ns)", "Duration")
        sync = np.array(["MemcpyDtoH" in n or "Synchronize" in n for n in names])
        ends = np.sort(a_end[sync])
        ends = ends[(ends >= start.min()) & (ends <= end.max())]
        # the gap each synchronising call ends in: from the call's return to the next kernel's start
        nxt = np.searchsorted(start, ends)
        ok = nxt < len(start)
        after = start[nxt[ok]] - ends[ok]
        out["after_sync"] = {"calls": int(ok.sum()), "to_next_kernel_s": float(after.sum() / 1e9),
                             "median_ms": float(np.median(after) / 1e6) if ok.any() else None,
                             "p90_ms": float(np.percentile(after, 90) / 1e6) if ok.any() else None}
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("gpu_trace", type=Path, help="nsys stats cuda_gpu_trace CSV")
    ap.add_argument("api_trace", type=Path, nargs="?", default=None, help="nsys stats cuda_api_trace CSV")
    ap.add_argument("--last-s", type=float, default=None, help="only this many seconds of the window ...")
    ap.add_argument("--skip-last-s", type=float, default=0.0, help="... ending this long before its end")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    out = {"benchmark": "gpu_timeline_gaps", "command": "python " + " ".join(sys.argv),
           **gaps_report(a.gpu_trace, a.api_trace, a.last_s, a.skip_last_s)}
    text = json.dumps(out, indent=1)
    print(text)
    if a.out is not None:
        a.out.write_text(text + "\n")
    return out


if __name__ == "__main__":
    main()
