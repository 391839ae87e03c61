"""``tracker: tensorboard`` (the default): TensorBoard event files under the run directory.

Written with the ``tensorboard`` package's own event writer (no TensorFlow, no torch): scalars as
``simple_value`` summaries, text through TensorBoard's text plugin, the spec's settings through its hparams
plugin, and figures as image summaries. View a run with
``tensorboard --logdir OUT/tensorboard``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from invphys.tracking.base import Tracker

log = logging.getLogger(__name__)

#: where the event files of a run go, relative to the run directory
LOGDIR = "tensorboard"


class TensorBoardTracker(Tracker):
    """Appends events to one ``events.out.tfevents.*`` file in ``logdir`` (opened on first use)."""

    name = "tensorboard"

    def __init__(self, logdir: str | Path, flush_secs: float = 10.0) -> None:
        self.logdir = Path(logdir)
        self.flush_secs = flush_secs
        self._writer: Any = None
        self._artifacts: list[str] = []

    @property
    def writer(self) -> Any:
        if self._writer is None:
            from tensorboard.summary.writer.event_file_writer import EventFileWriter

            self.logdir.mkdir(parents=True, exist_ok=True)
            self._writer = EventFileWriter(str(self.logdir), flush_secs=self.flush_secs)
            log.debug("TensorBoard events in %s", self.logdir)
        return self._writer

    def _add(self, summary: Any, step: int) -> None:
        from tensorboard.compat.proto.event_pb2 import Event

        self.writer.add_event(Event(wall_time=time.time(), step=int(step), summary=summary))

    def log_scalar(self, tag: str, value: float, step: int) -> None:
        from tensorboard.compat.proto.summary_pb2 import Summary

        self._add(Summary(value=[Summary.Value(tag=tag, simple_value=float(value))]), step)

    def log_text(self, tag: str, text: str) -> None:
        from tensorboard.plugins.text.summary_v2 import text_pb

        self._add(text_pb(tag, text), 0)

    def log_artifact(self, path: str | Path, name: str | None = None) -> None:
        """TensorBoard keeps no files: the artifact's path is listed in the ``artifacts`` text."""
        self._artifacts.append(f"- `{name or Path(path).name}`: {Path(path)}")
        self.log_text("artifacts", "\n".join(self._artifacts))

    def log_params(self, params: Mapping[str, Any]) -> None:
        """The settings through TensorBoard's hparams plugin (its HPARAMS tab; values as numbers, booleans or
        text)."""
        from tensorboard.plugins.hparams.summary_v2 import hparams_pb

        values = {str(k): v if isinstance(v, bool | int | float | str) else "null" if v is None else str(v)
                  for k, v in params.items()}
        values = {k: float(v) if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 2**53 else v
                  for k, v in values.items()}
        self._add(hparams_pb(values), 0)

    def log_image(self, tag: str, path: str | Path, step: int = 0) -> None:
        """A PNG figure as an image summary (the IMAGES tab); a file that is not a PNG is skipped."""
        from tensorboard.compat.proto.summary_pb2 import Summary

        data = Path(path).read_bytes()
        size = png_size(data)
        if size is None:
            log.warning("not a PNG image, not sent to TensorBoard: %s", path)
            return
        width, height, channels = size
        image = Summary.Image(height=height, width=width, colorspace=channels, encoded_image_string=data)
        self._add(Summary(value=[Summary.Value(tag=tag, image=image)]), step)

    def flush(self) -> None:
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None


#: channels of each PNG colour type (grey, RGB, palette, grey + alpha, RGBA)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}


def png_size(data: bytes) -> tuple[int, int, int] | None:
    """(width, height, channels) from a PNG's header, or None when ``data`` is not a PNG."""
    if len(data) < 26 or data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        return None
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return width, height, _PNG_CHANNELS.get(data[25], 4)
