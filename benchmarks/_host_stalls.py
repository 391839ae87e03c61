"""Where the main thread's time goes, sampled, and the garbage collector's pauses (``bench_dataset.py
--host-profile``).

A dataset's time split (``_time_split.py``) names the calls it wraps; the rest of the host's time between a
chunk's synchronising read and the next launch is unnamed (issue 16: ~6 ms per chunk, and a timeline showed
~1 s gaps). :class:`HostStalls` samples the main thread's stack from a thread of its own every ``interval``
seconds (a statistical profile: seconds per innermost frames) and times every collection of :mod:`gc` through
``gc.callbacks``. A sample is taken when the sampler gets the GIL, so a C call that holds it delays the sample
rather than hiding the time: the delay is counted against the frames found then, and long delays are listed,
as are stretches of consecutive samples at one place (a host stall of ~1 s shows as one).

The stack is read as text by :func:`faulthandler.dump_traceback`, which takes no reference to a frame: a
sampler holding a frame object could be the last owner of a finished function's locals and free them in its
own thread (a Taichi ndarray freed outside the thread of its CUDA context aborts the process). faulthandler
lists at most 100 threads, newest first: in a process with more, the sampled thread (usually the oldest) is
missing from the dump, and those samples are counted as missed (``missed_samples``), not attributed.
"""

from __future__ import annotations

import faulthandler
import gc
import re
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

_FRAME_LINE = re.compile(r'File "(.*)", line (\d+) in (\S+)')


def _where(dump: str, thread: int, depth: int) -> str | None:
    """The ``depth`` innermost frames of ``thread`` in a :func:`faulthandler.dump_traceback` text, innermost
    first, as ``file:function:line`` (None if the thread is not in it)."""
    head = f"0x{thread:016x}"
    parts: list[str] = []
    inside = False
    for line in dump.splitlines():
        if line.startswith(("Thread ", "Current thread ")):
            if inside:
                break
            inside = head in line
        elif inside and len(parts) < depth:
            m = _FRAME_LINE.search(line)
            if m:
                parts.append(f"{Path(m.group(1)).name}:{m.group(3)}:{m.group(2)}")
    return " < ".join(parts) if parts else None


class HostStalls:
    """Sample the calling thread's stack and time the garbage collector until the ``with`` block exits."""

    def __init__(self, interval: float = 0.005, depth: int = 4, long_s: float = 0.05, stretch_s: float = 0.2):
        self.interval, self.depth, self.long_s, self.stretch_s = interval, depth, long_s, stretch_s
        self.stretches: list[dict[str, Any]] = []   # consecutive samples at one place, > stretch_s in all
        self._run: list[Any] = [None, 0.0, 0.0]     # the current stretch: where, start, seconds
        self.seconds: Counter[str] = Counter()
        self.samples = 0
        self.missed, self.missed_s = 0, 0.0   # samples (and their seconds) that did not find the thread
        self.long_samples: list[dict[str, Any]] = []
        self.gc_pauses: list[tuple[int, float, float]] = []   # (generation, start offset s, pause s)
        self._target = threading.get_ident()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="host-stalls", daemon=True)
        self._gc_start: float | None = None
        self._t0 = 0.0

    def _on_gc(self, phase: str, info: dict[str, int]) -> None:
        now = time.perf_counter()
        if phase == "start":
            self._gc_start = now
        elif self._gc_start is not None:
            self.gc_pauses.append((int(info.get("generation", -1)), self._gc_start - self._t0, now - self._gc_start))
            self._gc_start = None

    def _sample(self) -> None:
        last = time.perf_counter()
        with tempfile.TemporaryFile("w+") as buf:
            while not self._stop.wait(self.interval):
                now = time.perf_counter()
                buf.seek(0)
                buf.truncate()
                faulthandler.dump_traceback(buf, all_threads=True)
                buf.seek(0)
                where = _where(buf.read(), self._target, self.depth)
                if where is None:   # not in the dump: faulthandler lists at most 100 threads, newest first
                    self.missed += 1
                    self.missed_s += now - last
                else:
                    self._count(where, now - last, last)
                last = now

    def _count(self, where: str, seconds: float, since: float) -> None:
        if where != self._run[0]:
            self._close_stretch()
            self._run = [where, since, 0.0]
        self._run[2] += seconds
        self.seconds[where] += seconds
        self.samples += 1
        if seconds > self.long_s:
            self.long_samples.append({"at_s": round(since - self._t0, 3), "s": round(seconds, 3), "where": where})

    def _close_stretch(self) -> None:
        where, start, seconds = self._run
        if where is not None and seconds > self.stretch_s:
            self.stretches.append({"at_s": round(start - self._t0, 3), "s": round(seconds, 3), "where": where})

    def __enter__(self) -> HostStalls:
        self._t0 = time.perf_counter()
        gc.callbacks.append(self._on_gc)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._close_stretch()
        gc.callbacks.remove(self._on_gc)

    def report(self, top: int = 25) -> dict[str, Any]:
        """The ``top`` places by sampled seconds, the long samples, and the collector's pauses by generation."""
        by_gen: dict[str, dict[str, float]] = {}
        for gen, _, pause in self.gc_pauses:
            g = by_gen.setdefault(str(gen), {"count": 0, "total_s": 0.0, "max_s": 0.0})
            g["count"] += 1
            g["total_s"] += pause
            g["max_s"] = max(g["max_s"], pause)
        return {"interval_s": self.interval, "samples": self.samples,
                "sampled_s": round(sum(self.seconds.values()), 3),
                "missed_samples": self.missed, "missed_s": round(self.missed_s, 3),
                "top": [{"s": round(s, 3), "where": w} for w, s in self.seconds.most_common(top)],
                "long_samples": sorted(self.long_samples, key=lambda x: -x["s"])[:top],
                "stretches": sorted(self.stretches, key=lambda x: -x["s"])[:top],
                "gc": {k: {"count": v["count"], "total_s": round(v["total_s"], 4), "max_s": round(v["max_s"], 4)}
                       for k, v in sorted(by_gen.items())},
                "gc_pauses_over_long_s": [{"generation": g, "at_s": round(t, 3), "s": round(p, 4)}
                                          for g, t, p in self.gc_pauses if p > self.long_s]}
