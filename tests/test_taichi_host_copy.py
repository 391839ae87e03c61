"""HostCopy: Taichi ndarrays read into new host arrays in one copy, equal to ``to_numpy`` (issue 16)."""

import numpy as np
import pytest

ti = pytest.importorskip("taichi")

from invphys_anisompm.backends.taichi_backend import ensure_taichi  # noqa: E402
from invphys_anisompm.backends.taichi_host_copy import HostCopy  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def _taichi_cpu() -> None:
    ensure_taichi("cpu")


def _filled(dtype, shape, values: np.ndarray):
    arr = ti.ndarray(dtype, shape)
    arr.from_numpy(values)
    return arr


def test_copies_equal_to_numpy_as_new_arrays() -> None:
    rng = np.random.default_rng(0)
    cases = [(ti.math.vec3, (4, 9), rng.normal(size=(4, 9, 3)).astype(np.float32)),
             (ti.math.mat3, (2, 5), rng.normal(size=(2, 5, 3, 3)).astype(np.float32)),
             (ti.f32, (3, 7), rng.normal(size=(3, 7)).astype(np.float32)),
             (ti.i32, (11,), rng.integers(-9, 9, size=11).astype(np.int32))]
    copy = HostCopy("cpu")
    for dtype, shape, values in cases:
        arr = _filled(dtype, shape, values)
        a, b = copy(arr), copy(arr)
        ref = arr.to_numpy()
        assert a.dtype == ref.dtype and a.shape == ref.shape
        assert np.array_equal(a, values) and np.array_equal(a, ref)
        assert not np.shares_memory(a, b)       # records may keep views: every read is a new array
        a[...] = 0
        assert np.array_equal(copy(arr), values)  # and writing into a copy leaves the device array alone
    assert copy.fallback is None


def test_a_copy_sees_the_kernels_launched_before_it() -> None:
    @ti.kernel
    def fill(a: ti.types.ndarray(ti.f32, 1), v: ti.f32):
        for i in a:
            a[i] = v + i

    arr = ti.ndarray(ti.f32, (1000,))
    copy = HostCopy("cpu")
    for v in (1.0, 5.0):
        fill(arr, v)
        assert np.array_equal(copy(arr), v + np.arange(1000, dtype=np.float32))


def test_a_refused_copy_falls_back_to_to_numpy_for_good() -> None:
    calls = []

    def refuse(dst, src, nbytes):
        calls.append(nbytes)
        return 201   # CUDA_ERROR_INVALID_CONTEXT: no context current in this thread

    values = np.arange(12, dtype=np.float32).reshape(3, 4)
    arr = _filled(ti.f32, (3, 4), values)
    copy = HostCopy("cpu")
    copy._dtoh = refuse
    assert np.array_equal(copy(arr), values)
    assert copy.fallback == "cuMemcpyDtoH returned CUresult 201"
    assert np.array_equal(copy(arr), values) and calls == [48]   # not tried again


def test_other_archs_use_to_numpy() -> None:
    copy = HostCopy("vulkan")
    assert copy.fallback == "no direct copy on arch 'vulkan'"
    values = np.ones((2, 3), np.float32)
    assert np.array_equal(copy(_filled(ti.f32, (2, 3), values)), values)


def test_the_wait_for_the_device_lets_other_threads_run() -> None:
    """On CUDA ``wait`` (every copy's) blocks in the driver's ``cuCtxSynchronize`` through ctypes, which
    releases the GIL, so that the process's other threads (extraction hand-off, stores) run while the GPU
    works rather than in the gap before the next launch. Here a ctypes ``usleep`` of 0.3 s stands in for the
    driver's wait: a pure-Python thread keeps stamping the time through the middle of it (a wait that held
    the GIL, as ``ti.sync()`` does, or ``ctypes.PyDLL``'s usleep, leaves no stamp inside)."""
    import ctypes
    import threading
    import time

    usleep = ctypes.CDLL(None).usleep
    usleep.argtypes = [ctypes.c_uint]
    window: list[float] = []

    def driver_wait() -> None:
        window.append(time.perf_counter())
        usleep(300_000)
        window.append(time.perf_counter())

    copy = HostCopy("cpu")
    copy._ctx_sync = driver_wait
    stamps: list[float] = []
    stop = threading.Event()

    def stamp() -> None:
        while not stop.is_set():
            stamps.append(time.perf_counter())

    worker = threading.Thread(target=stamp)
    worker.start()
    values = np.arange(6, dtype=np.float32)
    got = copy(_filled(ti.f32, (6,), values))
    stop.set()
    worker.join()
    assert np.array_equal(got, values) and len(window) == 2
    t = np.asarray(stamps)
    inside = ((t > window[0] + 0.05) & (t < window[1] - 0.05)).sum()
    assert inside > 100   # the thread ran in the middle of the wait
