"""``examples/anisompm/benchmarks/gpu_timeline_gaps.py`` (GPU idle gaps from an Nsight Systems trace) and
``bench_host_reads.py``'s CPU check of the direct reads and uploads (issue 16)."""

from __future__ import annotations

import csv
import json

import pytest
from engine_benchmarks import load


def _trace(path, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Start (ns)", "Duration (ns)", "Name"])
        w.writerows(rows)


def test_busy_share_gaps_and_the_gap_after_each_synchronising_copy(tmp_path):
    gaps = load("gpu_timeline_gaps")
    # kernels 0-10 us, 5-12 us (overlapping the first), 20-30 us, 1030-1040 us; a DtoH copy's own row is not a kernel
    _trace(tmp_path / "gpu.csv", [(0, 10_000, "p2g"), (5_000, 7_000, "g2p"), (20_000, 10_000, "grid"),
                                  (1_030_000, 10_000, "clear"), (12_500, 1_000, "[CUDA memcpy Device-to-Host]")])
    # the host's synchronising read returns at 30 us (the next kernel starts 1,000 us later); a launch is not a sync
    _trace(tmp_path / "api.csv", [(13_000, 17_000, "cuMemcpyDtoH_v2"), (15_000, 100, "cuLaunchKernel")])
    r = gaps.gaps_report(tmp_path / "gpu.csv", tmp_path / "api.csv")
    assert r["kernels"] == 4
    assert r["window_s"] == pytest.approx(1040e-6)
    assert r["idle_s"] == pytest.approx((8 + 1000) * 1e-6)       # 12-20 us and 30-1030 us
    assert r["busy_share"] == pytest.approx(32 / 1040)
    assert r["gaps_by_size"]["5-20 us"]["count"] == 1
    assert r["gaps_by_size"]["1000-5000 us"]["total_s"] == pytest.approx(1000e-6)
    assert r["after_sync"]["calls"] == 1 and r["after_sync"]["to_next_kernel_s"] == pytest.approx(1000e-6)
    # a window of the last 20 us ending 0 us before the end keeps only the last kernel: no gaps
    tail = gaps.gaps_report(tmp_path / "gpu.csv", None, last_s=20e-6)
    assert tail["kernels"] == 1 and tail["idle_s"] == 0.0 and "after_sync" not in tail


def test_host_reads_and_uploads_agree_both_ways_on_the_cpu(tmp_path):
    pytest.importorskip("taichi")
    bench = load("bench_host_reads")
    out = tmp_path / "reads.json"
    assert bench.main(["--preset", "tiny", "--arch", "cpu", "--batch", "4", "--slots", "2", "--repeats", "1",
                       "--out", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["same_arrays"] is True and got["frame_end_largest_relative_difference"] == 0.0
    assert set(got["times"]["set_frame"]) == {"from_numpy", "direct"}
