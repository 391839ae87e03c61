"""Native thread pools (BLAS, OpenMP, torch) of a worker process, limited for the process's lifetime.

Left alone, each of ``N`` worker processes starts one native thread per core of the host: on a 16-core
machine sixteen workers run 256 threads that wait on each other (answering measured 3x slower than one
process). Worker pools (feature extraction, answering in processes) call :func:`limit_threads` once at start.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS")


def limit_threads(threads: int | None) -> None:
    """This process's native thread pools on ``threads`` threads (None: leave them), for the libraries loaded
    already (threadpoolctl, torch) and those loaded later (the environment)."""
    if threads is None:
        return
    for var in THREAD_VARS:
        os.environ[var] = str(threads)
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=threads)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(threads)


def native_threads() -> dict[str, Any]:
    """This process's thread settings (for tests and benchmarks): the environment, threadpoolctl's pools and
    torch's intra-op threads (None where torch is not loaded)."""
    from threadpoolctl import threadpool_info

    torch = sys.modules.get("torch")
    return {"env": {v: os.environ.get(v) for v in THREAD_VARS},
            "pools": sorted({int(p["num_threads"]) for p in threadpool_info()}),
            "torch": torch.get_num_threads() if torch is not None else None}


__all__ = ["THREAD_VARS", "limit_threads", "native_threads"]
