"""The tracker interface: where training curves, final metrics and artifacts of a run go.

A tracker is created once per run (:func:`invphys.tracking.create_tracker`) and handed down to
whatever trains: the train stage's models (per-epoch losses), the goal-conditioned and per-objective
PPO optimisers (stable-baselines3's logger), and the runner (each stage's final metrics and its
artifacts). Tags are ``/``-separated paths (``surrogate/val_loss``); :meth:`Tracker.scoped` gives a
view that prefixes every tag, so a model logs ``train_loss`` without knowing where it sits in the run.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


class Tracker(ABC):
    """Receives scalars (with a step), text and artifact files of one run."""

    #: the ``tracker`` setting that creates this class
    name: str = "tracker"

    # -- to implement ---------------------------------------------------------------------------
    @abstractmethod
    def log_scalar(self, tag: str, value: float, step: int) -> None:
        """Record ``value`` of the series ``tag`` at ``step``."""

    def log_text(self, tag: str, text: str) -> None:
        """Record a piece of (markdown) text under ``tag``."""
        return None

    def log_artifact(self, path: str | Path, name: str | None = None) -> None:
        """Attach a file of the run (``name``: where it sits among the run's artifacts)."""
        return None

    def log_params(self, params: Mapping[str, Any]) -> None:
        """Record the run's settings once (flat ``section.key`` names, JSON-able values), to compare runs by."""
        return None

    def log_image(self, tag: str, path: str | Path, step: int = 0) -> None:
        """Record a figure (a PNG file) under ``tag``."""
        return None

    def flush(self) -> None:
        """Make what was logged so far visible to readers."""
        return None

    def close(self) -> None:
        """Flush and release the tracker; logging after ``close`` is an error of the caller."""
        return None

    # -- helpers --------------------------------------------------------------------------------
    def log_scalars(self, values: Mapping[str, Any], step: int, prefix: str = "") -> None:
        """Log every finite number in ``values`` (nested mappings become ``a/b`` tags) at ``step``."""
        for tag, value in flatten_numbers(values, prefix):
            self.log_scalar(tag, value, step)

    def scoped(self, prefix: str) -> Tracker:
        """A view of this tracker that prefixes every tag with ``prefix/``."""
        return ScopedTracker(self, prefix)

    def __enter__(self) -> Tracker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ScopedTracker(Tracker):
    """Forwards to a parent tracker with ``prefix/`` in front of every tag."""

    def __init__(self, parent: Tracker, prefix: str) -> None:
        self.parent = parent
        self.prefix = prefix.strip("/")
        self.name = parent.name

    def _tag(self, tag: str) -> str:
        return f"{self.prefix}/{tag}" if self.prefix else tag

    def log_scalar(self, tag: str, value: float, step: int) -> None:
        self.parent.log_scalar(self._tag(tag), value, step)

    def log_text(self, tag: str, text: str) -> None:
        self.parent.log_text(self._tag(tag), text)

    def log_artifact(self, path: str | Path, name: str | None = None) -> None:
        self.parent.log_artifact(path, name)

    def log_params(self, params: Mapping[str, Any]) -> None:
        self.parent.log_params({self._tag(k): v for k, v in params.items()})

    def log_image(self, tag: str, path: str | Path, step: int = 0) -> None:
        self.parent.log_image(self._tag(tag), path, step)

    def flush(self) -> None:
        self.parent.flush()

    def close(self) -> None:  # a view does not own the parent
        self.parent.flush()


class NullTracker(Tracker):
    """``tracker: none``: records nothing."""

    name = "none"

    def log_scalar(self, tag: str, value: float, step: int) -> None:
        pass


def flatten_numbers(values: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, float]]:
    """``(tag, value)`` for each finite int/float leaf of a nested mapping; lists and text are skipped."""
    for key, value in values.items():
        tag = f"{prefix}/{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            yield from flatten_numbers(value, tag)
        elif isinstance(value, bool) or value is None:
            continue
        elif isinstance(value, int | float) or _is_numpy_scalar(value):
            number = float(value)
            if math.isfinite(number):
                yield tag, number


def _is_numpy_scalar(value: Any) -> bool:
    return type(value).__module__ == "numpy" and getattr(value, "ndim", None) == 0


def flatten_params(values: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested settings as ``{"a.b.c": value}``: mappings are walked, lists of mappings become ``a.0.b``,
    other lists stay values (as JSON text); None is kept as ``None``."""
    import json

    out: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten_params(value, name) if value else {name: "{}"})
        elif isinstance(value, list | tuple) and value and all(isinstance(v, Mapping) for v in value):
            out.update(flatten_params({str(i): v for i, v in enumerate(value)}, name))
        elif isinstance(value, list | tuple):
            out[name] = json.dumps(list(value), default=str)
        else:
            out[name] = value
    return out
