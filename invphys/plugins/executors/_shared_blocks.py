"""Reusable shared-memory blocks for handing large arrays to worker processes without pickling them.

A pickled numpy array is copied into the pickle while the pickling thread holds the GIL (~13 ms for a
paper-preset orange-peel trajectory of 20 MB on an H100 host), which stalls the thread that drives the
GPU. :func:`pack` pickles an object with protocol 5, its array buffers kept out of band, and copies those
buffers into a :class:`SharedBlocks` block (numpy's copy releases the GIL); :func:`unpack` rebuilds the
object in the worker with its arrays as views of the block, so the worker copies nothing either.

Blocks are created by the parent, reused once released, and unlinked by :meth:`SharedBlocks.close` (or by
the interpreter's resource tracker if the parent dies). A block is made only where the shared-memory file
system has room for it (``posix_fallocate`` reserves its pages, so a full ``/dev/shm`` gives an error, not
a SIGBUS); otherwise :meth:`SharedBlocks.acquire` returns None and the caller pickles as usual.
"""

from __future__ import annotations

import os
import pickle
import threading
from multiprocessing import shared_memory
from typing import Any

import numpy as np

#: buffers start at multiples of this many bytes in a block (aligned arrays in the worker)
ALIGN = 64
_ATTACHED: dict[str, shared_memory.SharedMemory] = {}


def _aligned(n: int) -> int:
    return -(-int(n) // ALIGN) * ALIGN


class SharedBlocks:
    """At most ``max_blocks`` shared-memory blocks, each lent to one payload at a time."""

    def __init__(self, max_blocks: int, shm_dir: str = "/dev/shm") -> None:
        self.max_blocks = int(max_blocks)
        self.shm_dir = shm_dir
        self._free: list[shared_memory.SharedMemory] = []
        self._all: list[shared_memory.SharedMemory] = []
        self._lock = threading.Lock()
        self.created = 0

    def acquire(self, nbytes: int) -> shared_memory.SharedMemory | None:
        """A free block of at least ``nbytes`` (a new one while fewer than ``max_blocks`` exist and the
        file system has room), or None."""
        with self._lock:
            fits = [b for b in self._free if b.size >= nbytes]
            if fits:
                block = min(fits, key=lambda b: b.size)
                self._free.remove(block)
                return block
            if len(self._all) >= self.max_blocks:
                if not self._free:
                    return None
                self._retire(min(self._free, key=lambda b: b.size))  # too small for this payload: replace it
            block = self._create(_aligned(nbytes * 1.25 + ALIGN))
            if block is not None:
                self._all.append(block)
            return block

    def release(self, block: shared_memory.SharedMemory) -> None:
        """Give ``block`` back for reuse (its payload has been read)."""
        with self._lock:
            if block in self._all and block not in self._free:
                self._free.append(block)

    def close(self) -> None:
        """Unlink every block (call once no worker reads them any more)."""
        with self._lock:
            for block in list(self._all):
                self._retire(block)

    def _retire(self, block: shared_memory.SharedMemory) -> None:
        self._all.remove(block)
        if block in self._free:
            self._free.remove(block)
        try:
            block.close()
        except BufferError:  # a view of it is still alive here; the unlink below still frees the name
            pass
        try:
            block.unlink()
        except FileNotFoundError:
            pass

    def _create(self, size: int) -> shared_memory.SharedMemory | None:
        try:
            stat = os.statvfs(self.shm_dir)
        except OSError:
            return None   # no shared-memory file system we can see: pickle instead
        if stat.f_bavail * stat.f_frsize < 2 * size:
            return None
        try:
            block = shared_memory.SharedMemory(create=True, size=size)
        except OSError:   # no room, no permission: pickle instead
            return None
        fd = getattr(block, "_fd", -1)
        try:
            if fd >= 0 and hasattr(os, "posix_fallocate"):
                os.posix_fallocate(fd, 0, size)   # reserve the pages now: ENOSPC here, never SIGBUS later
        except OSError:
            block.close()
            block.unlink()
            return None
        self.created += 1
        return block


def pack(obj: Any, blocks: SharedBlocks, min_bytes: int) -> tuple[bytes, shared_memory.SharedMemory,
                                                                   list[tuple[int, int]]] | None:
    """``obj`` pickled with its out-of-band buffers copied into a block from ``blocks``: ``(pickle, block,
    spans)``; None when its buffers hold fewer than ``min_bytes`` or no block is free (pickle it instead)."""
    buffers: list[pickle.PickleBuffer] = []
    data = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    views = [np.frombuffer(b.raw(), dtype=np.uint8) for b in buffers]
    total = sum(_aligned(v.nbytes) for v in views)
    if not buffers or total < min_bytes:
        return None
    block = blocks.acquire(total)
    if block is None:
        return None
    spans, offset = [], 0
    dest = np.frombuffer(block.buf, dtype=np.uint8)
    for view in views:
        dest[offset:offset + view.nbytes] = view   # a plain memcpy: numpy releases the GIL
        spans.append((offset, offset + view.nbytes))
        offset += _aligned(view.nbytes)
    del dest
    return data, block, spans


def unpack(data: bytes, name: str, spans: list[tuple[int, int]]) -> Any:
    """The object :func:`pack` stored in block ``name`` (attached once per process), its arrays views of
    the block: valid until the parent reuses the block, i.e. for the task that received them."""
    block = _ATTACHED.get(name)
    if block is None:
        block = _ATTACHED[name] = shared_memory.SharedMemory(name=name)
    return pickle.loads(data, buffers=[block.buf[a:b] for a, b in spans])
