"""LaterCopies with its CUDA driver calls emulated on the CPU, for tests (an ndarray's memory is host memory
there): a queued copy is made only when its stream is waited for, the latest a real one can finish, so a reader
that lets its source be overwritten before it waits gets the new values and fails."""

from __future__ import annotations

import ctypes

from invphys_anisompm.backends import taichi_host_copy as hc


class FakeDriver:
    """``corrupt``: every copy leaves its last byte out."""

    NON_BLOCKING, NO_TIMING = 0x1, 0x2

    def __init__(self, corrupt: bool = False):
        self.corrupt = corrupt
        self.calls: list[str] = []
        self.queued: list[tuple[int, int, int]] = []
        self._keep: list[object] = []

    def check(self, status, what):
        if status != 0:
            raise OSError(f"{what} returned CUresult {status}")

    def cuStreamCreate(self, ref, flags):
        return 0

    def cuEventCreate(self, ref, flags):
        return 0

    def cuMemHostAlloc(self, ref, size, flags):
        buf = (ctypes.c_char * size)()
        self._keep.append(buf)
        ref._obj.value = ctypes.addressof(buf)
        return 0

    def cuEventRecord(self, event, stream):
        self.calls.append("record")
        return 0

    def cuStreamWaitEvent(self, stream, event, flags):
        self.calls.append("wait_event")
        return 0

    def cuMemcpyDtoHAsync(self, dst, src, n, stream):
        self.calls.append("copy")
        self.queued.append((dst, src, n - 1 if self.corrupt else n))
        return 0

    def cuStreamSynchronize(self, stream):
        self.calls.append("sync")
        for dst, src, n in self.queued:
            ctypes.memmove(dst, src, n)
        self.queued.clear()
        return 0


def fake_later_copies(host_copy: hc.HostCopy, capacity: int, corrupt: bool = False
                      ) -> tuple[hc.LaterCopies, FakeDriver]:
    """A LaterCopies on the CUDA path, its driver calls a :class:`FakeDriver`."""
    later = hc.LaterCopies("cpu", host_copy, capacity=capacity)
    fake = FakeDriver(corrupt)
    later.fallback = None
    orig = hc._CudaLater
    hc._CudaLater = lambda: fake  # type: ignore[assignment,misc]
    try:
        later._setup()
    finally:
        hc._CudaLater = orig
    return later, fake
