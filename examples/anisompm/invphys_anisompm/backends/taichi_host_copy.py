"""Taichi ndarrays copied into new host arrays in one copy (issue 16: the reads at a stream's frame end).

Taichi's ``to_numpy`` runs a kernel that writes into the host array; on CUDA it stages that array through a
device buffer: a copy to the device, the kernel, a copy back. At the paper preset a frame end reads ~60 runs'
particles (~50 MB) that way with the GPU idle: 25 ms on an H200's host, 17 ms with :class:`HostCopy`, which
copies the ndarray's own memory once (``cuMemcpyDtoH`` on CUDA, ``memmove`` on the CPU, where an ndarray lives
in host memory). Of those 17 ms, 12 are the new host array's first-touch page faults
(``benchmarks/bench_host_reads.py``).
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


class HostCopy:
    """``copy(arr)``: a new host array (``to_numpy``'s shape and dtype) holding Taichi ndarray ``arr``'s values,
    taken after every launched kernel has finished (``ti.sync()``).

    On ``arch`` "cuda" one device-to-host copy, on "cpu" a ``memmove``; anything else, or the first copy the
    driver refuses (no CUDA context current in this thread, say), uses ``to_numpy`` from then on, and
    ``fallback`` says why.

    On CUDA the wait for the GPU is the driver's ``cuCtxSynchronize`` through ctypes, which releases the GIL;
    Taichi's own ``ti.sync()`` (then immediate) holds it. Holding it for a frame end's ~20 ms wait kept the
    process's other threads (the extraction hand-off's stager and feeder, the store writer) from running until
    the wait was over, and then they took their turns in the gap before the next launch, with the GPU idle.
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
        src = ti.lang.impl.get_runtime().prog.get_ndarray_data_ptr_as_int(arr.arr)
        if self._dtoh is None:
            ctypes.memmove(out.ctypes.data, src, out.nbytes)
            return True
        status = self._dtoh(out.ctypes.data, src, out.nbytes)
        if status != 0:
            self.fallback = f"cuMemcpyDtoH returned CUresult {status}"
        return status == 0


__all__ = ["HostCopy"]
