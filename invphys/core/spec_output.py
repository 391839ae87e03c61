"""Where a command may write: an output directory that is no file, no bundle and lies in no dataset store."""

from __future__ import annotations

from pathlib import Path

from invphys.core.errors import InvphysError

#: files that mark a directory as an invphys dataset store, and an inverter bundle's manifest
STORE_MARKERS: tuple[str, ...] = ("_metadata.json", "_manifest.json")
BUNDLE_MANIFEST = "manifest.yaml"


def output_problem(path: str | Path, option: str = "--out", store_ok: bool = False) -> str | None:
    """Why ``path`` cannot be an output directory (None when it can), before anything is written.

    Refused: a path that is a file, lies under a file, or runs through a symlink loop; a path in or under
    an inverter bundle (``manifest.yaml`` with ``format_version``); a path in or under a dataset store
    (``store_ok``: the path itself may be a store, as ``dataset generate --out`` resumes one).
    """
    import errno
    import os
    import stat

    given = Path(path)
    out = Path(os.path.abspath(given))
    chain = [out, *out.parents]
    try:  # links followed too: a link to a folder inside a store is inside that store
        real = given.resolve()
        chain += [place for place in (real, *real.parents) if place not in chain]
    except (OSError, RuntimeError):  # a symbolic-link loop: found below
        pass
    for level, place in enumerate(chain):
        shown = str(given) if level == 0 else str(place)
        try:
            st = os.stat(place)
        except FileNotFoundError:
            continue
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                return (f"{option} {str(given)!r} is a symbolic-link loop" if level == 0 else
                        f"{option} {str(given)!r} runs through a symbolic-link loop ({shown!r})")
            if exc.errno == errno.ENOTDIR:
                continue  # a file above it: found at its own level
            return f"{option} {str(given)!r}: cannot look at {shown!r}: {exc.strerror or exc}"
        if not stat.S_ISDIR(st.st_mode):
            return (f"{option} {str(given)!r} is a file; name a new or existing directory" if level == 0
                    else f"{option} {str(given)!r} lies under {shown!r}, which is a file")
        if _is_bundle(place):
            where = "is" if level == 0 else f"lies inside {shown!r}, which is"
            return f"{option} {str(given)!r} {where} an inverter bundle; name a directory outside it"
        if any((place / m).is_file() for m in STORE_MARKERS) and not (store_ok and level == 0):
            where = "is" if level == 0 else f"lies inside {shown!r}, which is"
            return f"{option} {str(given)!r} {where} a dataset store; name a directory outside it"
    return None


def check_output_directory(path: str | Path, option: str = "--out", store_ok: bool = False) -> Path:
    """:func:`output_problem` as an :class:`InvphysError`; returns ``path``."""
    problem = output_problem(path, option, store_ok)
    if problem:
        raise InvphysError(problem)
    return Path(path)


def _is_bundle(directory: Path) -> bool:
    """True when ``directory`` holds an inverter bundle's manifest (a top-level ``format_version`` key)."""
    manifest = directory / BUNDLE_MANIFEST
    try:
        if not manifest.is_file():
            return False
        with manifest.open("rb") as fh:
            head = fh.read(65536)
    except OSError:
        return False
    return any(line.startswith(b"format_version:") for line in head.splitlines())
