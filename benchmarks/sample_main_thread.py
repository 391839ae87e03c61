"""Where a benchmark's main thread spends its time: a stack sampler around any script (issue 16).

Runs ``SCRIPT ARGS...`` in this process (``runpy``, as ``__main__``) while a daemon thread samples every
thread's Python stack each ``--interval`` seconds (``sys._current_frames``: no tracing, ~1 % overhead at 5 ms).
Writes, per thread kind (``main``, the others by name), the functions most often on the stack (inclusive: a
function counts once per sample it appears in) and at its top (leaf), as shares of that thread's samples.
A sample needs the GIL, so time inside a C call that holds it is seen late (attributed to what runs after);
a thread blocked in a call that releases the GIL (a GPU synchronisation, a pipe write) is seen there.

Example (one GPU; the dataset pipeline's main thread)::

    python benchmarks/sample_main_thread.py --out prof.json -- benchmarks/bench_dataset.py --preset paper \
        --arch cuda --n 512 --scheduling continuous --executors local --extract-workers 4 --out ds.json
"""

from __future__ import annotations

import argparse
import collections
import json
import runpy
import sys
import threading
import time
from pathlib import Path
from types import FrameType


def frame_names(frame: FrameType | None, limit: int = 200) -> list[str]:
    """``file:function`` of each frame from ``frame`` outwards (the leaf first)."""
    names: list[str] = []
    while frame is not None and len(names) < limit:
        code = frame.f_code
        names.append(f"{Path(code.co_filename).name}:{code.co_name}")
        frame = frame.f_back
    return names


class StackSampler:
    """Counts, per thread kind, the functions on the stack and at its top, every ``interval`` seconds."""

    def __init__(self, interval: float) -> None:
        self.interval = float(interval)
        self.samples: collections.Counter[str] = collections.Counter()
        self.inclusive: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
        self.leaf: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stack-sampler", daemon=True)

    def _run(self) -> None:
        me, main = threading.get_ident(), threading.main_thread().ident
        while not self._stop.wait(self.interval):
            names = {t.ident: t.name for t in threading.enumerate()}
            for ident, frame in sys._current_frames().items():
                if ident == me:
                    continue
                kind = "main" if ident == main else names.get(ident, "other").split("-")[0]
                stack = frame_names(frame)
                self.samples[kind] += 1
                self.leaf[kind][stack[0] if stack else "?"] += 1
                self.inclusive[kind].update(set(stack))

    def __enter__(self) -> StackSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def report(self, top: int) -> dict:
        """Per thread kind: samples, and the ``top`` inclusive and leaf functions as shares of them."""
        out = {}
        for kind, n in self.samples.most_common():
            out[kind] = {"samples": n,
                         "inclusive": {k: round(v / n, 4) for k, v in self.inclusive[kind].most_common(top)},
                         "leaf": {k: round(v / n, 4) for k, v in self.leaf[kind].most_common(top)}}
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--interval", type=float, default=0.005, help="seconds between samples")
    ap.add_argument("--top", type=int, default=60, help="functions kept per list")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("script", help="the script to run, then its arguments (after --)")
    ap.add_argument("args", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    rest = args.args[1:] if args.args[:1] == ["--"] else args.args
    sys.argv = [args.script, *rest]
    t0 = time.perf_counter()
    with StackSampler(args.interval) as sampler:
        try:
            runpy.run_path(args.script, run_name="__main__")
        finally:
            wall = time.perf_counter() - t0
    report = {"benchmark": "main_thread_samples", "script": args.script, "argv": sys.argv,
              "interval_s": args.interval, "wall_s": round(wall, 2), "threads": sampler.report(args.top)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"samples written to {args.out} ({wall:.1f} s)")


if __name__ == "__main__":
    main()
