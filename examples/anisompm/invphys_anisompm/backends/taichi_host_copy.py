"""Taichi ndarrays copied to and from host arrays in one copy (issue 16: a stream's reads and uploads between
chunks, with the GPU idle).

Taichi's ``to_numpy`` runs a kernel that writes into the host array; on CUDA it stages that array through a
device buffer: a copy to the device, the kernel, a copy back. At the paper preset a frame end reads ~60 runs'
particles (~50 MB) that way with the GPU idle: 25 ms on an H200's host, 17 ms with :class:`HostCopy`, which
copies the ndarray's own memory once (``cuMemcpyDtoH`` on CUDA, ``memmove`` on the CPU, where an ndarray lives
in host memory). Of those 17 ms, 12 are the new host array's first-touch page faults
(``benchmarks/bench_host_reads.py``).

``from_numpy`` is dearer still: Taichi's CUDA launcher treats a host array argument as in-out, so every upload
allocates a device buffer, copies the values in, synchronises, runs a kernel, synchronises again and copies them
back. :class:`HostUpload` copies the values into the ndarray's memory once instead (``cuMemcpyHtoD``).
"""

from __future__ import annotations

import ctypes

import numpy as np
import taichi as ti
from taichi.lang.util import to_numpy_type


def _cuda_driver_calls():
    """The driver's ``cuMemcpyDtoH`` (dst host pointer, src device address, bytes) -> CUresult and
    ``cuCtxSynchronize()`` -> CUresult, as ctypes functions (a ctypes call releases the GIL)."""
    lib = ctypes.CDLL("libcuda.so.1")
    dtoh = lib.cuMemcpyDtoH_v2
    dtoh.argtypes = [ctypes.c_void_p, ctypes.c_uint64, ctypes.c_size_t]
    dtoh.restype = ctypes.c_int
    sync = lib.cuCtxSynchronize
    sync.argtypes = []
    sync.restype = ctypes.c_int
    return dtoh, sync


def _cuda_memcpy_htod():
    """The driver's ``cuMemcpyHtoD`` (dst device address, src host pointer, bytes) -> CUresult."""
    htod = ctypes.CDLL("libcuda.so.1").cuMemcpyHtoD_v2
    htod.argtypes = [ctypes.c_uint64, ctypes.c_void_p, ctypes.c_size_t]
    htod.restype = ctypes.c_int
    return htod


def _data_ptr(arr) -> int:
    """The address of Taichi ndarray ``arr``'s memory (device memory on CUDA, host memory on the CPU)."""
    return ti.lang.impl.get_runtime().prog.get_ndarray_data_ptr_as_int(arr.arr)


class HostCopy:
    """``copy(arr)``: a new host array (``to_numpy``'s shape and dtype) holding Taichi ndarray ``arr``'s values,
    taken after every launched kernel has finished (``ti.sync()``).

    On ``arch`` "cuda" one device-to-host copy, on "cpu" a ``memmove``; anything else, or the first copy the
    driver refuses (no CUDA context current in this thread, say), uses ``to_numpy`` from then on, and
    ``fallback`` says why.

    On CUDA the wait for the GPU is the driver's ``cuCtxSynchronize`` through ctypes, which releases the GIL;
    Taichi's own ``ti.sync()`` (then immediate) holds it for the whole wait (~20 ms at a frame end). Released,
    the process's other threads (the extraction hand-off's stager and feeder, the store writer) run while the GPU
    works rather than in the gap before the next launch; two pairs of 512-run datasets on an H100 measured no
    difference beyond noise (``docs/gpu-throughput.md``, stop 45).
    """

    def __init__(self, arch: str):
        self.fallback: str | None = None
        self._dtoh = None
        self._ctx_sync = None
        if arch == "cuda":
            try:
                self._dtoh, self._ctx_sync = _cuda_driver_calls()
            except (OSError, AttributeError) as exc:
                self.fallback = f"no cuMemcpyDtoH in the CUDA driver: {exc}"
        elif arch != "cpu":
            self.fallback = f"no direct copy on arch {arch!r}"

    def __call__(self, arr) -> np.ndarray:
        if self.fallback is not None:
            return arr.to_numpy()
        out = np.empty(tuple(arr.arr.total_shape()), to_numpy_type(arr.dtype))
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


class HostUpload:
    """``upload(arr, values)``: Taichi ndarray ``arr`` takes host ``values`` (``to_numpy``'s shape; converted to
    its dtype), as ``arr.from_numpy(values)`` would, in one copy made after every launched kernel has finished
    (a chunk under way may still read ``arr``).

    On ``arch`` "cuda" one ``cuMemcpyHtoD`` (after :meth:`HostCopy.wait`), on "cpu" a ``memmove``. On CUDA the
    first upload is read back and compared bit for bit; a mismatch, a refused driver call, or any other arch
    uses ``from_numpy`` from then on, and ``fallback`` says why.
    """

    def __init__(self, arch: str, host_copy: HostCopy):
        self.fallback: str | None = None
        self._host_copy = host_copy
        self._htod = None
        self._checked = arch == "cpu"
        if arch == "cuda":
            try:
                self._htod = _cuda_memcpy_htod()
            except (OSError, AttributeError) as exc:
                self.fallback = f"no cuMemcpyHtoD in the CUDA driver: {exc}"
        elif arch != "cpu":
            self.fallback = f"no direct copy on arch {arch!r}"

    def __call__(self, arr, values: np.ndarray) -> None:
        shape = tuple(arr.arr.total_shape())
        values = np.ascontiguousarray(values, dtype=to_numpy_type(arr.dtype))
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


__all__ = ["HostCopy", "HostUpload"]
