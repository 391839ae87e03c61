"""A refine's log of finished runs (``--sim-refine-log``): a re-run replays them and simulates only the rest."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from invphys.core.safe_read import UserFileError

REFINE_LOG_FORMAT = "invphys.refine_log"
REFINE_LOG_VERSION = 1
_ARRAYS = {"format", "version", "key", "tid", "seq", "theta", "y", "seconds", "device"}


def _log_error(path: Path, problem: str) -> UserFileError:
    return UserFileError("refine log", path, problem)


class RunLog:
    """Every finished run of a refine, by (target id, run number); appended atomically every ``flush`` runs.

    ``key`` names what the runs depend on besides the target (bundle, simulator config): a log made for
    another key is refused, as is any existing file that is not a refine log (it is never overwritten);
    ``key`` None checks the file alone (before anything runs).
    """

    def __init__(self, path: str | Path | None, key: str | None, flush: int = 16) -> None:
        self.path = None if path is None else Path(path)
        self.key, self.flush = key, max(1, int(flush))
        self.rows: dict[tuple[str, int], tuple[np.ndarray, np.ndarray, float, str]] = {}
        self._unsaved = 0
        if self.path is not None:
            self._check()
            if self.path.exists():
                self._read()

    def _check(self) -> None:
        p = self.path
        assert p is not None
        if p.is_symlink() or p.is_dir():
            raise _log_error(p, "name a regular file (e.g. refine.npz)")
        parent = p.absolute().parent
        if not parent.is_dir():
            raise _log_error(p, f"{str(parent)!r} is not a directory")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise _log_error(p, f"cannot write in {str(parent)!r} (permission denied)")

    def _read(self) -> None:
        from invphys.core import safe_read

        p = self.path
        assert p is not None
        safe_read.check_regular_file(p, what="refine log", max_bytes=safe_read.NPZ_MAX_BYTES)
        with open(p, "rb") as fh:
            if fh.read(4) != b"PK\x03\x04":
                raise _log_error(p, "it exists and is not a refine log written by invphys; refusing to overwrite "
                                    "it (name another file)")
        z = safe_read.load_user_npz(p, what="refine log")
        if set(z) != _ARRAYS or str(z["format"]) != REFINE_LOG_FORMAT:
            raise _log_error(p, "it exists and is not a refine log written by invphys; refusing to overwrite it "
                                "(name another file)")
        if int(z["version"]) > REFINE_LOG_VERSION:
            raise _log_error(p, f"format version {int(z['version'])} is newer than this invphys reads; upgrade")
        if self.key is not None and str(z["key"]) != self.key:
            raise _log_error(p, "it was made for another bundle or simulator config; name another file, or remove "
                                "this one to refine afresh")
        try:
            tid, seq, theta, y = z["tid"], z["seq"], np.asarray(z["theta"], float), np.asarray(z["y"], float)
            sec, dev = np.asarray(z["seconds"], float), z["device"]
            if not (len(tid) == len(seq) == len(theta) == len(y) == len(sec) == len(dev)) or theta.ndim != 2:
                raise ValueError("its arrays differ in length")
            for i in range(len(tid)):
                self.rows[(str(tid[i]), int(seq[i]))] = (theta[i], y[i], float(sec[i]), str(dev[i]))
        except (ValueError, TypeError, IndexError) as exc:
            raise _log_error(p, f"corrupt refine log ({exc}); move it away or name another file") from None

    def get(self, tid: str, seq: int, theta: np.ndarray) -> tuple[np.ndarray, float, str] | None:
        """The logged features, seconds and device of run ``seq`` of target ``tid`` at ``theta`` (else None)."""
        row = self.rows.get((tid, seq))
        if row is None or row[0].shape != theta.shape or not np.allclose(row[0], theta, rtol=0.0, atol=1e-9):
            return None
        return row[1], row[2], row[3]

    def add(self, tid: str, seq: int, theta: np.ndarray, y: np.ndarray, seconds: float, device: str) -> None:
        self.rows[(tid, seq)] = (np.array(theta, float), np.array(y, float), float(seconds), device)
        self._unsaved += 1
        if self._unsaved >= self.flush:
            self.save()

    def save(self) -> None:
        """Write every run so far (atomically)."""
        if self.path is None or not self._unsaved:
            return
        from invphys.core.atomic import atomic_write_bytes

        keys = sorted(self.rows)
        vals = [self.rows[k] for k in keys]
        buf = io.BytesIO()
        np.savez_compressed(buf, format=np.array(REFINE_LOG_FORMAT), version=np.array(REFINE_LOG_VERSION),
                            key=np.array(self.key or ""), tid=np.array([k[0] for k in keys], dtype=str),
                            seq=np.array([k[1] for k in keys], dtype=np.int64),
                            theta=np.stack([v[0] for v in vals]), y=np.stack([v[1] for v in vals]),
                            seconds=np.array([v[2] for v in vals], float),
                            device=np.array([v[3] for v in vals], dtype=str))
        try:
            atomic_write_bytes(self.path, buf.getvalue())
        except OSError as exc:
            raise _log_error(self.path, f"cannot write it: {exc.strerror or exc}") from None
        self._unsaved = 0


__all__ = ["REFINE_LOG_FORMAT", "REFINE_LOG_VERSION", "RunLog"]
