"""Taichi ndarrays copied to and from host arrays in one copy (issue 16: a stream's reads and uploads between
chunks, with the GPU idle).

Taichi's ``to_numpy`` runs a kernel that writes into the host array; on CUDA it stages that array through a
device buffer: a copy to the device, the kernel, a copy back. At the paper preset a frame end reads ~60 runs'
particles (~50 MB) that way with the GPU idle: 25 ms on an H200's host, 17 ms with :class:`HostCopy`, which
copies the ndarray's own memory once (``cuMemcpyDtoH`` on CUDA, ``memmove`` on the CPU, where an ndarray lives
in host memory). Of those 17 ms, 12 are the new host array's first-touch page faults
(``examples/anisompm/benchmarks/bench_host_reads.py``).

``from_numpy`` is dearer still: Taichi's CUDA launcher treats a host array argument as in-out, so every upload
allocates a device buffer, copies the values in, synchronises, runs a kernel, synchronises again and copies them
back. :class:`HostUpload` copies the values into the ndarray's memory once instead (``cuMemcpyHtoD``).
"""

from __future__ import annotations

import ctypes
import logging

import numpy as np
import taichi as ti
from taichi.lang.util import to_numpy_type

from invphys_anisompm.backends import ReadyRead

log = logging.getLogger(__name__)


def _cuda_driver_calls():
    """The driver's ``cuMemcpyDtoH`` (dst host pointer, src device address, bytes) -> CUresult and a wait for
    Taichi's stream, ``cuStreamSynchronize(NULL)`` -> CUresult (what ``ti.sync()`` does: Taichi launches on the
    legacy default stream; :class:`LaterCopies`' own stream is not waited for), as ctypes functions (a ctypes
    call releases the GIL)."""
    lib = ctypes.CDLL("libcuda.so.1")
    dtoh = lib.cuMemcpyDtoH_v2
    dtoh.argtypes = [ctypes.c_void_p, ctypes.c_uint64, ctypes.c_size_t]
    dtoh.restype = ctypes.c_int
    stream_sync = lib.cuStreamSynchronize
    stream_sync.argtypes = [ctypes.c_void_p]
    stream_sync.restype = ctypes.c_int
    return dtoh, lambda: stream_sync(None)


def _cuda_memcpy_htod():
    """The driver's ``cuMemcpyHtoD`` (dst device address, src host pointer, bytes) -> CUresult."""
    htod = ctypes.CDLL("libcuda.so.1").cuMemcpyHtoD_v2
    htod.argtypes = [ctypes.c_uint64, ctypes.c_void_p, ctypes.c_size_t]
    htod.restype = ctypes.c_int
    return htod


def _host_layout(arr) -> tuple[tuple[int, ...], np.dtype, int]:
    """Taichi ndarray ``arr``'s host form, as ``to_numpy`` gives it: shape, dtype and size in bytes."""
    shape, dtype = tuple(arr.arr.total_shape()), np.dtype(to_numpy_type(arr.dtype))
    return shape, dtype, int(np.prod(shape)) * dtype.itemsize


class _MayFallBack:
    """``fallback``: None while the direct path is used, else why not; the first reason is logged as a warning
    (the slower Taichi path is then taken for good), unless it is only the arch's (set ``_fallback`` then)."""

    _fallback: str | None = None

    @property
    def fallback(self) -> str | None:
        return self._fallback

    @fallback.setter
    def fallback(self, why: str | None) -> None:
        if why is not None and self._fallback is None:
            log.warning("%s falls back to Taichi's own path: %s", type(self).__name__, why)
        self._fallback = why


def _data_ptr(arr) -> int:
    """The address of Taichi ndarray ``arr``'s memory (device memory on CUDA, host memory on the CPU)."""
    return ti.lang.impl.get_runtime().prog.get_ndarray_data_ptr_as_int(arr.arr)


class HostCopy(_MayFallBack):
    """``copy(arr)``: a new host array (``to_numpy``'s shape and dtype) holding Taichi ndarray ``arr``'s values,
    taken after every launched kernel has finished (``ti.sync()``).

    On ``arch`` "cuda" one device-to-host copy, on "cpu" a ``memmove``; anything else, or the first copy the
    driver refuses (no CUDA context current in this thread, say), uses ``to_numpy`` from then on, and
    ``fallback`` says why.

    On CUDA the wait for the GPU is the driver's ``cuStreamSynchronize`` through ctypes, which releases the GIL;
    Taichi's own ``ti.sync()`` (then immediate) holds it for the whole wait (~20 ms at a frame end). Released,
    the process's other threads (the extraction hand-off's stager and feeder, the store writer) run while the GPU
    works rather than in the gap before the next launch; two pairs of 512-run datasets on an H100 measured no
    difference beyond noise (``docs/gpu-throughput.md``, stop 45).
    """

    def __init__(self, arch: str):
        self._dtoh = None
        self._ctx_sync = None
        if arch == "cuda":
            try:
                self._dtoh, self._ctx_sync = _cuda_driver_calls()
            except (OSError, AttributeError) as exc:
                self.fallback = f"no cuMemcpyDtoH in the CUDA driver: {exc}"
        elif arch != "cpu":
            self._fallback = f"no direct copy on arch {arch!r}"

    def __call__(self, arr) -> np.ndarray:
        if self.fallback is not None:
            return arr.to_numpy()
        shape, dtype, _ = _host_layout(arr)
        out = np.empty(shape, dtype)
        return out if self._copy_into(out, arr) else arr.to_numpy()

    def wait(self) -> None:
        """Wait until every launched kernel has finished, on CUDA with the GIL released while the GPU works
        (a refused driver call only leaves the wait to ``ti.sync()``)."""
        if self._ctx_sync is not None:
            self._ctx_sync()
        ti.sync()

    def _copy_into(self, out: np.ndarray, arr) -> bool:
        """Copy ``arr``'s memory into the host array ``out`` (of its size); False (and ``fallback`` set) if the
        driver refused."""
        self.wait()   # the kernels that write arr have finished
        src = _data_ptr(arr)
        if self._dtoh is None:
            ctypes.memmove(out.ctypes.data, src, out.nbytes)
            return True
        status = self._dtoh(out.ctypes.data, src, out.nbytes)
        if status != 0:
            self.fallback = f"cuMemcpyDtoH returned CUresult {status}"
        return status == 0


class HostUpload(_MayFallBack):
    """``upload(arr, values)``: Taichi ndarray ``arr`` takes host ``values`` (``to_numpy``'s shape; converted to
    its dtype), as ``arr.from_numpy(values)`` would, in one copy made after every launched kernel has finished
    (a chunk under way may still read ``arr``).

    On ``arch`` "cuda" one ``cuMemcpyHtoD`` (after :meth:`HostCopy.wait`), on "cpu" a ``memmove``. On CUDA the
    first upload is read back and compared bit for bit; a mismatch, a refused driver call, or any other arch
    uses ``from_numpy`` from then on, and ``fallback`` says why.
    """

    def __init__(self, arch: str, host_copy: HostCopy):
        self._host_copy = host_copy
        self._htod = None
        self._checked = arch == "cpu"
        if arch == "cuda":
            try:
                self._htod = _cuda_memcpy_htod()
            except (OSError, AttributeError) as exc:
                self.fallback = f"no cuMemcpyHtoD in the CUDA driver: {exc}"
        elif arch != "cpu":
            self._fallback = f"no direct copy on arch {arch!r}"

    def __call__(self, arr, values: np.ndarray) -> None:
        shape, dtype, _ = _host_layout(arr)
        values = np.ascontiguousarray(values, dtype=dtype)
        if values.shape != shape:
            raise ValueError(f"values of shape {values.shape} for an ndarray of shape {shape}")
        if self.fallback is None and self._copy_into(arr, values):
            if self._checked:
                return
            self._checked = True
            if self._host_copy(arr).tobytes() == values.tobytes():
                return
            self.fallback = "the first direct upload read back different values"
        arr.from_numpy(values)

    def _copy_into(self, arr, values: np.ndarray) -> bool:
        """Copy ``values`` into ``arr``'s memory; False (and ``fallback`` set) if the driver refused."""
        self._host_copy.wait()   # no launched kernel still reads arr
        dst = _data_ptr(arr)
        if self._htod is None:
            ctypes.memmove(dst, values.ctypes.data, values.nbytes)
            return True
        status = self._htod(dst, values.ctypes.data, values.nbytes)
        if status != 0:
            self.fallback = f"cuMemcpyHtoD returned CUresult {status}"
        return status == 0


class _CudaLater:
    """The driver calls of :class:`LaterCopies` on CUDA (ctypes; each releases the GIL)."""

    NON_BLOCKING, NO_TIMING = 0x1, 0x2

    def __init__(self) -> None:
        lib = ctypes.CDLL("libcuda.so.1")
        ptr, vp, u64, size, uint = ctypes.POINTER(ctypes.c_void_p), ctypes.c_void_p, ctypes.c_uint64, \
            ctypes.c_size_t, ctypes.c_uint
        spec = {"cuStreamCreate": [ptr, uint], "cuEventCreate": [ptr, uint], "cuEventRecord": [vp, vp],
                "cuStreamWaitEvent": [vp, vp, uint], "cuMemHostAlloc": [ptr, size, uint],
                "cuMemcpyDtoHAsync_v2": [vp, u64, size, vp], "cuStreamSynchronize": [vp]}
        for name, argtypes in spec.items():
            fn = getattr(lib, name)
            fn.argtypes, fn.restype = argtypes, ctypes.c_int
            setattr(self, name.removesuffix("_v2"), fn)

    def check(self, status: int, what: str) -> None:
        if status != 0:
            raise OSError(f"{what} returned CUresult {status}")


class LaterCopies(_MayFallBack):
    """Device-to-host copies that finish while the GPU goes on (issue 16: a frame end's particle reads).

    ``start(arrays)`` queues copies of Taichi ndarrays ``arrays``, ordered after every kernel launched so far,
    and returns a handle whose ``result()`` gives new host arrays (as :class:`HostCopy` would). On CUDA the
    copies run on a stream of their own, after an event on Taichi's stream, into one pinned host buffer
    (``capacity`` bytes), so that the host can launch the next chunk at once and take the arrays later while the
    chunk runs; ``result()`` waits for the copies only, then copies the pinned bytes into new arrays. Until a
    handle's ``result()`` the ndarrays must not be written (the caller's gather buffers). One read is in flight
    at a time: ``start`` completes the previous one first. Elsewhere, and on CUDA when the driver refuses a call,
    a copy exceeds ``capacity``, or the first read differs from a synchronous one (checked bit for bit),
    ``start`` reads synchronously (``fallback`` says why).
    """

    def __init__(self, arch: str, host_copy: HostCopy, capacity: int):
        self._fallback = None if arch == "cuda" else f"synchronous reads on arch {arch!r}"
        self._host_copy = host_copy
        self._capacity = int(capacity)
        self._cuda: _CudaLater | None = None
        self._stream = self._event = self._pinned = None
        self._checked = False
        self._last: _LaterRead | None = None

    def _setup(self) -> None:
        cu = _CudaLater()
        stream, event, pinned = ctypes.c_void_p(), ctypes.c_void_p(), ctypes.c_void_p()
        cu.check(cu.cuStreamCreate(ctypes.byref(stream), cu.NON_BLOCKING), "cuStreamCreate")
        cu.check(cu.cuEventCreate(ctypes.byref(event), cu.NO_TIMING), "cuEventCreate")
        cu.check(cu.cuMemHostAlloc(ctypes.byref(pinned), max(self._capacity, 1), 0), "cuMemHostAlloc")
        self._cuda, self._stream, self._event, self._pinned = cu, stream, event, pinned

    def settle(self) -> None:
        """Complete the read in flight, if any (before its ndarrays are written again)."""
        if self._last is not None:
            self._last.result()
            self._last = None

    def start(self, arrays: tuple) -> ReadyRead | _LaterRead:
        self.settle()   # its bytes leave the pinned buffer before new ones arrive
        specs = [_host_layout(a) for a in arrays]
        nbytes = sum(n for _, _, n in specs)
        if self.fallback is None and nbytes > self._capacity:
            self.fallback = f"a read of {nbytes} bytes exceeds the pinned buffer's {self._capacity}"
        if self.fallback is None:
            try:
                if self._cuda is None:
                    self._setup()
                read = self._start(arrays, specs)
            except (OSError, AttributeError) as exc:
                self.fallback = f"no copies on a stream of their own: {exc}"
            else:
                if not self._checked:   # the first one against a synchronous read of the same arrays
                    self._checked = True
                    later = read.result()
                    now = tuple(self._host_copy(a) for a in arrays)
                    if all(x.tobytes() == y.tobytes() for x, y in zip(later, now, strict=True)):
                        return ReadyRead(later)
                    self.fallback = "the first read on its own stream differed from a synchronous one"
                    return ReadyRead(now)
                self._last = read
                return read
        return ReadyRead(tuple(self._host_copy(a) for a in arrays))

    def _start(self, arrays: tuple, specs: list) -> _LaterRead:
        cu = self._cuda
        assert cu is not None and self._pinned is not None and self._pinned.value is not None
        cu.check(cu.cuEventRecord(self._event, None), "cuEventRecord")   # Taichi launches on the legacy stream
        cu.check(cu.cuStreamWaitEvent(self._stream, self._event, 0), "cuStreamWaitEvent")
        offset, views = 0, []
        for a, (shape, dt, n) in zip(arrays, specs, strict=True):
            cu.check(cu.cuMemcpyDtoHAsync(self._pinned.value + offset, _data_ptr(a), n, self._stream),
                     "cuMemcpyDtoHAsync")
            views.append((offset, shape, dt))
            offset += n
        return _LaterRead(self, arrays, views)

    def _wait_and_take(self, views: list) -> tuple[np.ndarray, ...]:
        cu = self._cuda
        assert cu is not None and self._pinned is not None and self._pinned.value is not None
        cu.check(cu.cuStreamSynchronize(self._stream), "cuStreamSynchronize")
        offset, shape, dt = views[-1]
        buf = (ctypes.c_char * (offset + int(np.prod(shape)) * dt.itemsize)).from_address(self._pinned.value)
        return tuple(np.frombuffer(buf, dt, int(np.prod(shape)), off).reshape(shape).copy()
                     for off, shape, dt in views)


class _LaterRead:
    """A :class:`LaterCopies` read in flight; ``result()`` waits for it once and returns new host arrays."""

    def __init__(self, owner: LaterCopies, sources: tuple, views: list):
        self._owner, self._sources, self._views = owner, sources, views
        self._arrays: tuple[np.ndarray, ...] | None = None

    def result(self) -> tuple[np.ndarray, ...]:
        if self._arrays is None:
            try:
                self._arrays = self._owner._wait_and_take(self._views)
            except OSError as exc:   # the sources are still intact: read them synchronously
                self._owner.fallback = f"no copies on a stream of their own: {exc}"
                self._arrays = tuple(self._owner._host_copy(a) for a in self._sources)
            if self._owner._last is self:
                self._owner._last = None
        return self._arrays


__all__ = ["HostCopy", "HostUpload", "LaterCopies"]
