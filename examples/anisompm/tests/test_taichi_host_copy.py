"""HostCopy and HostUpload: Taichi ndarrays read into new host arrays and written from host arrays in one copy,
equal to ``to_numpy`` and ``from_numpy`` (issue 16)."""

import numpy as np
import pytest

ti = pytest.importorskip("taichi")

from fake_cuda_copies import fake_later_copies  # noqa: E402
from invphys_anisompm.backends.taichi_backend import ensure_taichi  # noqa: E402
from invphys_anisompm.backends.taichi_host_copy import HostCopy, HostUpload, LaterCopies  # noqa: E402


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


def test_a_refused_copy_falls_back_to_to_numpy_for_good_and_says_so_once(caplog) -> None:
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
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == ["HostCopy falls back to Taichi's own path: cuMemcpyDtoH returned CUresult 201"]


def test_other_archs_use_to_numpy_without_a_warning(caplog) -> None:
    copy = HostCopy("vulkan")
    assert copy.fallback == "no direct copy on arch 'vulkan'" and not caplog.records
    values = np.ones((2, 3), np.float32)
    assert np.array_equal(copy(_filled(ti.f32, (2, 3), values)), values)


def test_the_wait_for_the_device_lets_other_threads_run() -> None:
    """On CUDA ``wait`` (every copy's) blocks in the driver's ``cuStreamSynchronize`` through ctypes, which
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


def test_uploads_equal_from_numpy() -> None:
    rng = np.random.default_rng(1)
    cases = [(ti.math.vec3, (4, 9), rng.normal(size=(4, 9, 3))),
             (ti.math.mat3, (2, 5), rng.normal(size=(2, 5, 3, 3))),
             (ti.f32, (3, 7), rng.normal(size=(3, 7))),
             (ti.i32, (11,), rng.integers(-9, 9, size=11))]   # int64 and float64 in: converted as from_numpy's callers did
    upload = HostUpload("cpu", HostCopy("cpu"))
    for dtype, shape, values in cases:
        arr, ref = ti.ndarray(dtype, shape), ti.ndarray(dtype, shape)
        upload(arr, values)
        ref.from_numpy(values.astype(ref.to_numpy().dtype))
        assert np.array_equal(arr.to_numpy(), ref.to_numpy())
    assert upload.fallback is None
    with pytest.raises(ValueError, match="shape"):
        upload(ti.ndarray(ti.f32, (3,)), np.zeros(4))


def test_an_upload_waits_for_the_kernels_launched_before_it_and_kernels_see_it() -> None:
    @ti.kernel
    def total(a: ti.types.ndarray(ti.f32, 1), out: ti.types.ndarray(ti.f32, 1)):
        for i in a:
            out[0] += a[i]

    arr, out = ti.ndarray(ti.f32, (100,)), ti.ndarray(ti.f32, (1,))
    upload = HostUpload("cpu", HostCopy("cpu"))
    for v in (1.0, 3.0):
        upload(arr, np.full(100, v))
        upload(out, np.zeros(1))
        total(arr, out)
        assert out.to_numpy()[0] == 100 * v


def test_a_direct_upload_that_reads_back_wrong_or_is_refused_falls_back_to_from_numpy_for_good() -> None:
    """The CUDA path (emulated on the CPU: ``_htod`` a stand-in, the first upload checked): a copy that leaves
    other values in the ndarray, or a refused driver call, hands every upload to ``from_numpy`` from then on."""
    import ctypes

    values = np.arange(12, dtype=np.float32).reshape(3, 4)
    calls = []

    def wrong(dst, src, nbytes):   # copies only half of the bytes
        calls.append(nbytes)
        ctypes.memmove(dst, src, nbytes // 2)
        return 0

    arr = _filled(ti.f32, (3, 4), np.zeros((3, 4), np.float32))
    upload = HostUpload("cpu", HostCopy("cpu"))
    upload._htod, upload._checked = wrong, False
    upload(arr, values)
    assert np.array_equal(arr.to_numpy(), values)
    assert upload.fallback == "the first direct upload read back different values"
    upload(arr, values + 1)
    assert np.array_equal(arr.to_numpy(), values + 1) and calls == [48]   # not tried again

    def refuse(dst, src, nbytes):
        return 201

    upload = HostUpload("cpu", HostCopy("cpu"))
    upload._htod, upload._checked = refuse, False
    upload(arr, values)
    assert np.array_equal(arr.to_numpy(), values) and upload.fallback == "cuMemcpyHtoD returned CUresult 201"


def test_a_correct_direct_upload_is_checked_once_then_trusted() -> None:
    import ctypes

    calls = []

    def right(dst, src, nbytes):
        calls.append(nbytes)
        ctypes.memmove(dst, src, nbytes)
        return 0

    arr = ti.ndarray(ti.i32, (5,))
    upload = HostUpload("cpu", HostCopy("cpu"))
    upload._htod, upload._checked = right, False
    for v in range(3):
        upload(arr, np.full(5, v))
        assert np.array_equal(arr.to_numpy(), np.full(5, v))
    assert upload.fallback is None and upload._checked and calls == [20, 20, 20]


def _later(corrupt: bool = False, capacity: int = 1 << 16):
    later = LaterCopies("cpu", HostCopy("cpu"), capacity=capacity)
    assert later.fallback == "synchronous reads on arch 'cpu'"
    return fake_later_copies(HostCopy("cpu"), capacity, corrupt)


def test_later_reads_give_new_arrays_equal_to_synchronous_reads() -> None:
    rng = np.random.default_rng(2)
    x = _filled(ti.math.vec3, (3, 50), rng.normal(size=(3, 50, 3)).astype(np.float32))
    d = _filled(ti.f32, (3, 50), rng.random((3, 50)).astype(np.float32))
    later, fake = _later()
    first = later.start((x, d))     # the first read is checked against a synchronous one, then returned
    assert later.fallback is None and np.array_equal(first.result()[0], x.to_numpy())
    n = len(fake.calls)
    read = later.start((x, d))
    assert fake.calls[n:] == ["record", "wait_event", "copy", "copy"]   # queued after the event, not waited for
    xs, ds = read.result()
    assert fake.calls[-1] == "sync"
    assert np.array_equal(xs, x.to_numpy()) and np.array_equal(ds, d.to_numpy())
    assert xs.dtype == np.float32 and xs.shape == (3, 50, 3) and ds.shape == (3, 50)
    assert read.result()[0] is xs                              # taken once
    again = later.start((x, d))
    assert not np.shares_memory(again.result()[0], xs)        # every read is a new array (records keep views)


def test_a_new_later_read_completes_the_one_in_flight_first() -> None:
    a = _filled(ti.f32, (4,), np.arange(4, dtype=np.float32))
    later, fake = _later()
    later.start((a,)).result()
    pending = later.start((a,))
    later.settle()                                   # what a gather into the same buffers does first
    assert fake.calls[-1] == "sync" and pending._arrays is not None
    assert np.array_equal(pending.result()[0], np.arange(4))


def test_later_reads_that_differ_or_do_not_fit_fall_back_to_synchronous_reads() -> None:
    values = np.arange(10, dtype=np.float32)
    a = _filled(ti.f32, (10,), values)
    later, _ = _later(corrupt=True)
    assert np.array_equal(later.start((a,)).result()[0], values)   # the synchronous read is returned
    assert later.fallback == "the first read on its own stream differed from a synchronous one"
    later, fake = _later(capacity=16)
    assert np.array_equal(later.start((a,)).result()[0], values)
    assert later.fallback == "a read of 40 bytes exceeds the pinned buffer's 16" and "copy" not in fake.calls
