"""Reading a simulator's continuous-batching stream up to where it breaks.

Dataset workers and the simulator validator both run rows through :meth:`Simulator.simulate_stream` and,
when the stream itself raises (a run that blew up, a device error), re-run the rows it did not return
through :meth:`Simulator.simulate`, where a failing row fails alone. :func:`stream_until_broken` is the
shared first half; :func:`unreturned` names the rows for the second.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError

log = logging.getLogger(__name__)


def stream_until_broken(simulator: Any, params: np.ndarray, batch_size: int | None,
                        seen: set[int]) -> Iterator[tuple[int, Any]]:
    """Yield ``(row, result)`` from ``simulator.simulate_stream(params, batch_size)``, adding each row to
    ``seen``. A stream that raises ends the generator quietly (logged), except an :class:`InvphysError`
    (the user's to fix), which propagates; what the caller raises while handling a row is never caught
    here. Rows missing from ``seen`` afterwards (:func:`unreturned`) are the caller's to re-run."""
    stream = iter(simulator.simulate_stream(params, batch_size))
    try:
        while True:
            try:
                i, res = next(stream)
            except StopIteration:
                return
            except InvphysError:
                raise
            except Exception as exc:
                log.warning("the simulator's stream broke after %d of %d rows (%s: %s); the rest are re-run "
                            "in batches", len(seen), len(params), type(exc).__name__, exc)
                return
            seen.add(int(i))
            yield int(i), res
    finally:
        close = getattr(stream, "close", None)
        if close is not None:
            close()


def unreturned(n_rows: int, seen: set[int]) -> list[int]:
    """Rows ``0..n_rows-1`` that a stream did not return, in row order."""
    return [r for r in range(n_rows) if r not in seen]


__all__ = ["stream_until_broken", "unreturned"]
