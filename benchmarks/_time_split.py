"""Where a streamed dataset's wall time goes: seconds inside chosen methods, and a generator's consumer time.

:class:`TimeSplit` patches methods of classes for the length of a ``with`` block: :meth:`~TimeSplit.wrap` adds
the time spent inside each call (a synchronising read's time is mostly the GPU's), and
:meth:`~TimeSplit.wrap_generator` splits a generator method's wall into the time inside it (producing the next
item) and the time its consumer spends between items (with continuous batching, work the GPU overlaps only if
it is shorter than the chunk running meanwhile). Used by ``bench_dataset.py --time-split``.
"""

from __future__ import annotations

import functools
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from typing import Any

#: marks a patched method that ``cls`` inherited (restored by deleting the patch)
_INHERITED = object()


def _inherited(cls: type, name: str) -> Any:
    """``name`` as defined on ``cls`` or the first base in its MRO that defines it (the function, unbound)."""
    for klass in cls.__mro__:
        if name in klass.__dict__:
            return klass.__dict__[name]
    raise AttributeError(f"{cls.__name__} has no {name!r}")


class TimeSplit:
    """Seconds and calls per label, gathered by patched methods until the block exits."""

    def __init__(self) -> None:
        self.seconds: defaultdict[str, float] = defaultdict(float)
        self.calls: Counter[str] = Counter()
        self._undo: list[tuple[type, str, Any]] = []

    def wrap(self, cls: type, name: str, label: str | None = None) -> None:
        """Time every call of ``cls.name`` under ``label`` (default ``Class.name``)."""
        original = _inherited(cls, name)
        key = label or f"{cls.__name__}.{name}"

        @functools.wraps(original)
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds[key] += time.perf_counter() - t0
                self.calls[key] += 1

        self._patch(cls, name, original, timed)

    def wrap_generator(self, cls: type, name: str, label: str | None = None) -> None:
        """Split the iteration of generator method ``cls.name`` into ``<label> inside`` (producing items) and
        ``<label> consumer`` (the caller's time between receiving an item and asking for the next)."""
        original = _inherited(cls, name)
        key = label or f"{cls.__name__}.{name}"

        @functools.wraps(original)
        def timed(*args: Any, **kwargs: Any) -> Iterator[Any]:
            inner = original(*args, **kwargs)
            handed_out: float | None = None
            try:
                while True:
                    t0 = time.perf_counter()
                    if handed_out is not None:
                        self.seconds[f"{key} consumer"] += t0 - handed_out
                        self.calls[f"{key} consumer"] += 1
                    try:
                        item = next(inner)
                    except StopIteration:
                        return
                    finally:
                        self.seconds[f"{key} inside"] += time.perf_counter() - t0
                    self.calls[f"{key} inside"] += 1
                    handed_out = time.perf_counter()
                    yield item
            finally:
                inner.close()

        self._patch(cls, name, original, timed)

    def _patch(self, cls: type, name: str, original: Any, replacement: Callable[..., Any]) -> None:
        own = name in cls.__dict__  # a method inherited from a base is patched on ``cls`` and removed after
        setattr(cls, name, replacement)
        self._undo.append((cls, name, original if own else _INHERITED))

    def report(self, wall_s: float) -> dict[str, Any]:
        """Per label: seconds, share of ``wall_s`` and calls."""
        return {"wall_s": round(wall_s, 3),
                "split": {k: {"s": round(v, 3), "share": round(v / wall_s, 4) if wall_s else None,
                              "calls": int(self.calls.get(k, 0))}
                          for k, v in sorted(self.seconds.items(), key=lambda kv: -kv[1])}}

    def __enter__(self) -> TimeSplit:
        return self

    def __exit__(self, *exc: object) -> None:
        for cls, name, original in reversed(self._undo):
            if original is _INHERITED:
                delattr(cls, name)
            else:
                setattr(cls, name, original)
        self._undo.clear()
