"""The bounded reader under :mod:`invphys.core.safe_read` and :mod:`invphys.core.safe_yaml`: a regular file of at
most a size limit, read in chunks that stop at the limit, as UTF-8 text without NUL bytes (a BOM dropped).
Refusals are one :class:`UserFileError` line. Import these through :mod:`invphys.core.safe_read`, which
re-exports them; this module exists so that the YAML parser can read files without importing the formats
that use it.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

from invphys.core.errors import InvphysError

#: largest text, JSON or CSV file read (bytes): target files, manifests
DEFAULT_MAX_BYTES = 32 << 20
_BOM = b"\xef\xbb\xbf"


class UserFileError(InvphysError, ValueError):
    """A file handed to invphys is not what it should be; the message is ``"<what> '<path>': <problem>"``
    (``"cannot read <what> '<path>': <reason>"`` when the system refused to open it)."""

    def __init__(self, what: str, path: str | os.PathLike[str], problem: str, message: str | None = None) -> None:
        self.what, self.path, self.problem = what, str(path), problem
        super().__init__(message or f"{what} {str(path)!r}: {problem}")


class Problem(InvphysError):
    """A parser's complaint, before the file it is about is put in front of it."""


def _oserror(what: str, path: Path, exc: OSError) -> UserFileError:
    reason = exc.strerror or str(exc)
    return UserFileError(what, path, f"cannot read it: {reason}", f"cannot read {what} {str(path)!r}: {reason}")


def size_text(n: int) -> str:
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if n >= 1 << shift and n % (1 << shift) == 0:
            return f"{n >> shift} {unit}"
    return f"{n:,} bytes"


def check_regular_file(path: str | os.PathLike[str], *, what: str, max_bytes: int = DEFAULT_MAX_BYTES) -> Path:
    """``path`` when it is an existing regular file of at most ``max_bytes`` bytes (``os.stat``, nothing
    opened); else :class:`UserFileError` saying which of these it is not."""
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as exc:
        raise _oserror(what, p, exc) from None
    except ValueError as exc:  # a NUL character in the name
        raise UserFileError(what, p, f"not a usable file name ({exc})") from None
    if stat.S_ISDIR(st.st_mode):
        raise UserFileError(what, p, "it is a directory, not a file")
    if not stat.S_ISREG(st.st_mode):
        raise UserFileError(what, p, "not a regular file (a device, pipe or socket)")
    if st.st_size > max_bytes:
        raise UserFileError(what, p, f"{st.st_size:,} bytes, over the {size_text(max_bytes)} limit for a {what}")
    return p


def _read_at_most(fh: Any, limit: int, chunk: int = 1 << 20) -> bytes:
    """Up to ``limit`` bytes in chunks: memory grows with what the file holds, never with the limit."""
    out = bytearray()
    while len(out) < limit:
        block = fh.read(min(chunk, limit - len(out)))
        if not block:
            break
        out += block
    return bytes(out)


def read_user_bytes(path: str | os.PathLike[str], *, what: str, max_bytes: int = DEFAULT_MAX_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (:func:`check_regular_file`); the read stops
    at the limit, so a file that grows meanwhile is refused too."""
    p = check_regular_file(path, what=what, max_bytes=max_bytes)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):  # swapped for a FIFO after the stat
                raise UserFileError(what, p, "not a regular file (a device, pipe or socket)")
            data = _read_at_most(fh, max_bytes + 1)
    except OSError as exc:
        raise _oserror(what, p, exc) from None
    if len(data) > max_bytes:
        raise UserFileError(what, p, f"over the {size_text(max_bytes)} limit for a {what}")
    return data


def text_of(data: bytes) -> str:
    """``data`` as UTF-8 text, a leading BOM dropped; binary content refused naming its line (an
    :class:`~invphys.core.errors.InvphysError` whose message is the problem alone)."""
    if data.startswith(_BOM):
        data = data[len(_BOM):]
    nul = data.find(b"\x00")
    if nul >= 0:
        line = data.count(b"\n", 0, nul) + 1
        raise Problem(f"not a text file (a NUL byte on line {line})")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise Problem(f"not UTF-8 text (byte 0x{data[exc.start]:02x} on line {line})") from None


def decode_text(data: bytes, *, what: str, path: str | os.PathLike[str]) -> str:
    """``data`` as UTF-8 text (:func:`text_of`), refusals as :class:`UserFileError`."""
    try:
        return text_of(data)
    except Problem as exc:
        raise UserFileError(what, path, str(exc)) from None


def read_user_text(path: str | os.PathLike[str], *, what: str, max_bytes: int = DEFAULT_MAX_BYTES) -> str:
    """The UTF-8 text of a regular file of at most ``max_bytes`` (a BOM dropped; see :func:`decode_text`)."""
    return decode_text(read_user_bytes(path, what=what, max_bytes=max_bytes), what=what, path=path)
