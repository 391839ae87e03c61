"""The extraction timeout where features are extracted in the process that simulates: the ``local``
executor with ``extract_workers: 0`` (its default), the ``process`` executor's workers, Ray tasks and
actors, and the simulator validator. (Extraction processes, ``extract_workers >= 1``, have their own:
:mod:`._extract_pool`.)

What happens to an extraction that runs past ``timeout_s``:

1. In the main thread of a POSIX process whose ``SIGALRM`` is free (default handler, no timer running),
   a timer (``setitimer``) fires after ``timeout_s``; its handler raises into the extractor's Python code
   wherever it is (a loop, a ``sleep``, a lock or I/O wait) an exception that is not an ``Exception`` (an
   extractor's ``except Exception`` cannot swallow it), its ``finally`` blocks run, and the run becomes an
   :class:`~._extract_pool.ExtractionTimedOut` failure; the executor goes on with the next runs.
2. An extractor stuck in native code that never comes back to Python (the handler cannot run) cannot be
   stopped inside a process without ending it. In a process that exists only to run batches (a ``process``
   executor's worker, a Ray worker or actor: ``disposable``), faulthandler's watchdog thread, which needs no
   GIL, writes the stacks to stderr and ends the process ``min(timeout_s, 30)`` seconds after the timeout;
   the executor handles it as a worker that died (the batch's rows re-run alone, the stuck one recorded as
   failed). In the local executor's own process (the user's run) nothing is ended: the run waits for it.
3. Elsewhere (not the main thread, Windows, ``SIGALRM`` in use by other code) there is no in-process
   timeout: one warning says so; ``extract_workers >= 1`` gives one.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any, TypeVar

from invphys.core.errors import SimulationFailed

_LOG = logging.getLogger(__name__)
T = TypeVar("T")

#: a process that only runs batches (a process pool worker, a Ray worker): a native hang may end it
DISPOSABLE = False
_ARMED = False
_WARNED = False


class ExtractionTimedOut(SimulationFailed):
    """One run's feature extraction took longer than the extraction timeout (``extract_timeout_s``): it was
    interrupted here, or its extraction process was stopped (and replaced). That run's failure."""


class _Expired(BaseException):
    """Raised into the extractor by the timer (a BaseException: ``except Exception`` lets it through)."""


def _on_alarm(signum: int, frame: Any) -> None:
    if _ARMED:
        raise _Expired()


def _alarm_free() -> bool:
    """Whether this thread may use ``SIGALRM`` for the deadline."""
    if not hasattr(signal, "setitimer") or threading.current_thread() is not threading.main_thread():
        return False
    handler = signal.getsignal(signal.SIGALRM)
    if handler not in (signal.SIG_DFL, _on_alarm):
        return False
    return signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)


def _hard_stop_after(timeout_s: float) -> float:
    return timeout_s + min(timeout_s, 30.0)


def _arm_hard_stop(timeout_s: float) -> bool:
    """faulthandler's watchdog on the process's real stderr (``sys.stderr`` may be a capture without a file
    descriptor, e.g. under a test runner); False where it cannot be armed (no hard stop then)."""
    import faulthandler

    try:
        faulthandler.dump_traceback_later(_hard_stop_after(timeout_s), exit=True, file=sys.__stderr__)
    except (AttributeError, OSError, TypeError, ValueError):  # io.UnsupportedOperation is an OSError/ValueError
        return False
    return True


def call(fn: Callable[..., T], timeout_s: float | None, *args: Any) -> T:
    """``fn(*args)`` under the extraction timeout (see the module's text): raises ExtractionTimedOut."""
    global _ARMED, _WARNED
    if timeout_s is None:
        return fn(*args)
    if not _alarm_free():
        if not _WARNED:
            _WARNED = True
            _LOG.warning("the extraction timeout is not enforced for extraction in %s (it needs the main thread "
                         "of a POSIX process with SIGALRM free); set extract_workers >= 1 to have one",
                         "this thread" if sys.platform != "win32" else "this process")
        return fn(*args)
    hard = DISPOSABLE and _arm_hard_stop(timeout_s)
    previous = signal.signal(signal.SIGALRM, _on_alarm)
    try:
        _ARMED = True
        signal.setitimer(signal.ITIMER_REAL, timeout_s)
        try:
            return fn(*args)
        finally:
            _ARMED = False   # first: a timer that fires from here on raises nothing
    except _Expired:
        raise ExtractionTimedOut(f"feature extraction took longer than {timeout_s:g} s (the extraction "
                                 "timeout); it was interrupted and the run recorded as failed") from None
    finally:
        _ARMED = False
        signal.setitimer(signal.ITIMER_REAL, 0)
        if hard:
            import faulthandler

            faulthandler.cancel_dump_traceback_later()
        signal.signal(signal.SIGALRM, previous)
