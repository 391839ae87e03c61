"""``benchmarks/_time_split.py`` and ``bench_dataset.py --time-split``: where a streamed dataset's wall goes
(time inside patched methods, a generator's production against its consumer), and the patches undone."""

from __future__ import annotations

import time

import pytest
from benchmark_modules import BENCHMARKS, load


class _Producer:
    def work(self, seconds: float) -> float:
        time.sleep(seconds)
        return seconds

    def items(self, n: int):
        try:
            for i in range(n):
                time.sleep(0.02)   # producing each item
                yield i
        finally:
            self.closed = True


def test_time_inside_methods_and_a_generators_consumer_are_split_and_the_patches_undone(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    from _time_split import TimeSplit

    original_work, original_items = _Producer.__dict__["work"], _Producer.__dict__["items"]
    p = _Producer()
    with TimeSplit() as split:
        split.wrap(_Producer, "work")
        split.wrap_generator(_Producer, "items", "items")
        assert p.work(0.03) == 0.03 and p.work(0.01) == 0.01
        got = []
        for i in p.items(5):
            got.append(i)
            time.sleep(0.04)   # the consumer's time between items
        early = p.items(5)
        next(early)
        early.close()          # closing the wrapper closes the generator it wraps
    assert got == [0, 1, 2, 3, 4] and p.closed
    assert _Producer.__dict__["work"] is original_work and _Producer.__dict__["items"] is original_items
    s, calls = split.seconds, split.calls
    assert calls["_Producer.work"] == 2 and s["_Producer.work"] == pytest.approx(0.04, abs=0.03)
    assert calls["items inside"] == 6 and s["items inside"] == pytest.approx(0.12, abs=0.06)
    assert calls["items consumer"] == 5 and s["items consumer"] == pytest.approx(0.20, abs=0.06)
    report = split.report(1.0)
    assert next(iter(report["split"])) == "items consumer" and report["split"]["items consumer"]["share"] > 0.1


def test_bench_dataset_time_split_on_a_real_tiny_stream():
    pytest.importorskip("taichi")
    bench = load("bench_dataset")
    out = bench.bench("tiny", 2, 2, ["local"], 1, 6, "taichi", 0, arch="cpu", scheduling="continuous",
                      extract_workers=[1], time_split=True)
    res = out["results"]["local_extract1"]
    split = res["time_split"]["split"]
    assert res["ok"] == 2
    for key in ("stream inside", "stream consumer", "advance (launch)", "hand-off to extraction (caller)",
                "store append", "frame_end (synchronising read: GPU wait + statistics)"):
        assert split[key]["calls"] > 0, key
    assert split["stream inside"]["calls"] == 2 and split["hand-off to extraction (caller)"]["calls"] == 2
    assert split["stream inside"]["s"] + split["stream consumer"]["s"] <= res["time_split"]["wall_s"]
    assert split["advance (launch)"]["s"] <= split["stream inside"]["s"]   # launches happen inside the stream
    from invphys_anisompm.backends.taichi_backend import TaichiBackend

    assert not hasattr(TaichiBackend.advance, "__wrapped__")   # patches undone


def _slow_part(seconds: float) -> None:
    time.sleep(seconds)


def test_host_stalls_finds_where_the_main_thread_waits_and_times_gc_pauses(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import gc

    from _host_stalls import HostStalls

    junk = [[i] for i in range(200_000)]   # tracked containers: a full collection has work to do
    with HostStalls(interval=0.002) as stalls:
        _slow_part(0.3)
        gc.collect()
    del junk
    report = stalls.report()
    top = report["top"][0]
    assert "_slow_part" in top["where"] and top["s"] == pytest.approx(0.3, abs=0.1)
    assert report["sampled_s"] >= 0.3 and report["samples"] > 50
    assert report["gc"]["2"]["count"] >= 1 and report["gc"]["2"]["max_s"] > 0
    stretch = report["stretches"][0]   # the 0.3 s sleep as one stretch at one place
    assert "_slow_part" in stretch["where"] and stretch["s"] == pytest.approx(0.3, abs=0.1)
    assert gc.callbacks.count(stalls._on_gc) == 0 and not stalls._thread.is_alive()   # undone


def test_bench_dataset_host_profile_on_a_real_tiny_stream():
    pytest.importorskip("taichi")
    bench = load("bench_dataset")
    out = bench.bench("tiny", 2, 2, ["local"], 1, 6, "taichi", 0, arch="cpu", scheduling="continuous",
                      extract_workers=[0], host_profile=True)
    prof = out["results"]["local"]["host_profile"]
    assert prof["samples"] > 10 and any("streaming.py" in t["where"] for t in prof["top"])


class _FreedIn:
    """Records the thread in which it is freed (a Taichi ndarray must be freed in its CUDA context's thread)."""

    threads: set[int] = set()

    def __del__(self) -> None:
        import threading

        _FreedIn.threads.add(threading.get_ident())


def _short_call() -> None:
    local = _FreedIn()   # noqa: F841 - freed when the call's frame goes
    time.sleep(0.0002)


def test_host_stalls_never_frees_the_sampled_threads_locals(monkeypatch):
    """A sampler that kept a frame object could be the last owner of a returned call's locals and free them
    in its own thread (it aborted a CUDA run); the stack is read as text instead."""
    import threading

    monkeypatch.syspath_prepend(str(BENCHMARKS))
    from _host_stalls import HostStalls

    _FreedIn.threads.clear()
    with HostStalls(interval=0.0005) as stalls:
        for _ in range(3000):
            _short_call()
    assert stalls.samples > 100 and any("_short_call" in t["where"] for t in stalls.report()["top"])
    assert _FreedIn.threads == {threading.get_ident()}
