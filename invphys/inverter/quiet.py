"""Third-party output through logging: what sbi, torch or cma print or warn while answering goes to the
``invphys.thirdparty`` logger at debug level (``invphys -v`` shows it), so stdout holds only the answer."""

from __future__ import annotations

import contextlib
import io
import logging
import warnings
from collections.abc import Iterator

LOG = logging.getLogger("invphys.thirdparty")


class _LogStream(io.TextIOBase):
    """A text stream whose complete lines become debug records."""

    def __init__(self) -> None:
        self._buf = ""

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        self._buf += text
        *lines, self._buf = self._buf.split("\n")
        for line in lines:
            if line.strip():
                LOG.debug("%s", line.rstrip())
        return len(text)

    def flush(self) -> None:
        if self._buf.strip():
            LOG.debug("%s", self._buf.rstrip())
        self._buf = ""


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Inside: ``print`` to stdout and ``warnings`` become debug log records (nested use is fine)."""
    stream = _LogStream()
    with contextlib.redirect_stdout(stream), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield
        finally:
            stream.flush()
    for w in caught:
        LOG.debug("%s: %s", w.category.__name__, w.message)
