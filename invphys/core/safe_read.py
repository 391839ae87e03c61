"""One bounded reader for every file a user or a shared artifact hands invphys.

Target files (``--target``, a spec's ``targets.file``), bundle manifests, polish logs, trajectories and
dataset parts are read through these functions; specs too (:mod:`invphys.core.safe_yaml` reads its
files with :func:`read_user_text`). The byte and text reader lives in :mod:`invphys.core.bounded_read` (re-exported
here), below both this module and the YAML parser. Each refuses, with one :class:`UserFileError` line
``"<what> '<path>': <problem>"`` and before reading anything large:

* what is not a regular file: a directory, a FIFO (``os.stat`` only: nothing is opened, so a FIFO
  never blocks), a device such as ``/dev/zero``, a socket;
* a file over its size limit, by its size (a sparse file of 1 GB is refused without reading it);
  reads stop at the limit even when the file grows meanwhile;
* text that is not UTF-8 or holds a NUL byte (a leading UTF-8 BOM, as spreadsheets write, is dropped);
* YAML: the alias, depth and duplicate-key limits of :mod:`invphys.core.safe_yaml` (both lines named);
* JSON: a key given twice in one object (both lines named);
* CSV: two header columns of the same name (both columns named);
* integers too large for a float (more than about 1e308), in YAML and JSON alike;
* ``.npz`` archives: truncated or corrupt ones, other members than arrays, pickled objects (never
  loaded), an array header claiming more bytes than its member holds, more unpacked bytes than the limit.

JSON's ``NaN`` and ``Infinity`` literals (which Python's own writer emits) are read as floats: the
reader's caller decides, as a target refuses any value that is not finite, naming its feature.

Limits (a caller may pass others): :data:`DEFAULT_MAX_BYTES` for text, JSON and CSV files,
:data:`YAML_MAX_BYTES` and :data:`YAML_MAX_NODES` for YAML data files, :data:`NPZ_MAX_BYTES` and
:data:`NPZ_MAX_UNPACKED` for ``.npz`` archives (their arrays unpacked).
"""

from __future__ import annotations

import csv
import io
import json
import os
import sys
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from invphys.core.bounded_read import DEFAULT_MAX_BYTES as DEFAULT_MAX_BYTES
from invphys.core.bounded_read import Problem as _Problem
from invphys.core.bounded_read import UserFileError as UserFileError
from invphys.core.bounded_read import check_regular_file as check_regular_file
from invphys.core.bounded_read import decode_text as decode_text
from invphys.core.bounded_read import read_user_bytes as read_user_bytes
from invphys.core.bounded_read import read_user_text as read_user_text
from invphys.core.bounded_read import size_text as _size
from invphys.core.bounded_read import text_of as text_of
from invphys.core.errors import InvphysError

#: largest YAML data file (bytes; YAML parses far slower than JSON or CSV: this one within seconds)
YAML_MAX_BYTES = 4 << 20
#: most values a YAML data file may expand to (aliases expanded)
YAML_MAX_NODES = 1_000_000
#: largest ``.npz`` file read (bytes): trajectories, polish logs
NPZ_MAX_BYTES = 2 << 30
#: most bytes the arrays of one ``.npz`` file may unpack to
NPZ_MAX_UNPACKED = 4 << 30
#: most decimal digits of an integer (larger ones are not numbers a float can hold)
MAX_INT_DIGITS = 309

# -- YAML ----------------------------------------------------------------------------------------------------
def loads_user_yaml(text: str, *, source: str, max_bytes: int = YAML_MAX_BYTES,
                    max_nodes: int = YAML_MAX_NODES) -> Any:
    """Parse YAML ``text`` with the limits of :func:`invphys.core.safe_yaml.load` (one document, depth,
    aliases, duplicate keys, huge integers); refusals are :class:`InvphysError` starting with ``source``."""
    from invphys.core import safe_yaml

    data, _ = safe_yaml.load(text, source=source, error=InvphysError, limit=max_bytes, max_nodes=max_nodes,
                             fast=True)
    return data


def load_user_yaml(path: str | os.PathLike[str], *, what: str, max_bytes: int = YAML_MAX_BYTES,
                   max_nodes: int = YAML_MAX_NODES) -> Any:
    """The YAML file ``path`` parsed (:func:`read_user_text`, then :func:`loads_user_yaml`)."""
    from invphys.core import safe_yaml

    text = read_user_text(path, what=what, max_bytes=max_bytes)
    try:
        data, _ = safe_yaml.load(text, source="", error=_Problem, limit=max_bytes, max_nodes=max_nodes, fast=True)
    except _Problem as exc:
        raise UserFileError(what, path, str(exc).removeprefix(": ")) from None
    return data


# -- JSON ----------------------------------------------------------------------------------------------------
class _Duplicate(Exception):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise _Duplicate(k)
        out[k] = v
    return out


def _parse_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS or abs(value := int(text)) > sys.float_info.max:
        raise _Problem(f"the integer {text[:12]}... ({digits} digits) is too large for a number (at most ~1e308)")
    return value


def loads_user_json(text: str, *, source: str) -> Any:
    """Parse JSON ``text``: a key given twice in one object and integers too large for a float are
    refused (:class:`InvphysError` starting with ``source``); ``NaN``/``Infinity`` are floats."""
    try:
        return _json(text)
    except _Problem as exc:
        raise InvphysError(f"{source}: {exc}") from None


def _json(text: str) -> Any:
    try:
        return json.loads(text, object_pairs_hook=_pairs, parse_int=_parse_int)
    except json.JSONDecodeError as exc:
        raise _Problem(f"not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except _Duplicate as dup:
        lines = _duplicate_lines(text, dup.key) if len(text) <= 4 << 20 else None  # (a slower second parse)
        where = f" (lines {lines[0]} and {lines[1]})" if lines else ""
        raise _Problem(f"key {dup.key!r} appears twice in one object{where}") from None
    except RecursionError:
        raise _Problem("nested too deeply") from None


def _duplicate_lines(text: str, key: str) -> tuple[int, int] | None:
    """The lines of the first key given twice in one object (a second, position-keeping parse)."""
    from json import decoder, scanner

    found: list[tuple[int, int]] = []

    def parse_object(s_and_end: tuple[str, int], strict: bool, scan_once: Any, *rest: Any) -> Any:
        starts: list[int] = []

        def recording(s: str, idx: int) -> Any:
            starts.append(idx)
            return scan_once(s, idx)

        def check(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
            first: dict[str, int] = {}
            for (k, _), at in zip(pairs, starts, strict=False):
                if k in first and not found:
                    found.append((text.count("\n", 0, first[k]) + 1, text.count("\n", 0, at) + 1))
                first.setdefault(k, at)
            return dict(pairs)

        obj_hook, _pairs_hook, memo = rest[0], rest[1], rest[2]
        return decoder.JSONObject(s_and_end, strict, recording, obj_hook, check, memo)  # type: ignore[attr-defined]

    dec: Any = json.JSONDecoder(parse_int=lambda s: 0)
    dec.parse_object = parse_object
    dec.scan_once = scanner.py_make_scanner(dec)  # type: ignore[attr-defined]  # calls parse_object
    try:
        dec.decode(text)
    except (ValueError, RecursionError):
        return None
    return found[0] if found else None


def load_user_json(path: str | os.PathLike[str], *, what: str, max_bytes: int = DEFAULT_MAX_BYTES) -> Any:
    """The JSON file ``path`` parsed (:func:`read_user_text`, then :func:`loads_user_json`)."""
    text = read_user_text(path, what=what, max_bytes=max_bytes)
    try:
        return _json(text)
    except _Problem as exc:
        raise UserFileError(what, path, str(exc)) from None


# -- CSV -----------------------------------------------------------------------------------------------------
@dataclass
class CsvTable:
    """A CSV file's header (names stripped of spaces), its rows of strings and each row's line number."""

    header: list[str]
    rows: list[list[str]]
    lines: list[int]


def parse_user_csv(text: str, *, what: str, path: str | os.PathLike[str]) -> CsvTable:
    """Parse CSV ``text``: a header of distinct names, then rows (blank lines skipped)."""
    reader = csv.reader(io.StringIO(text, newline=""))
    rows: list[list[str]] = []
    lines: list[int] = []
    try:
        header = [h.strip() for h in next(reader, [])]
        for row in reader:
            if row and any(cell.strip() for cell in row):
                rows.append(row)
                lines.append(reader.line_num)
    except csv.Error as exc:
        raise UserFileError(what, path, f"not valid CSV (line {reader.line_num}: {exc})") from None
    if not header or not any(header):
        raise UserFileError(what, path, "empty CSV (expected a header of column names)")
    seen: dict[str, int] = {}
    for j, name in enumerate(header, start=1):
        if name in seen:
            raise UserFileError(what, path, f"columns {seen[name]} and {j} are both named {name!r}")
        seen[name] = j
    return CsvTable(header=header, rows=rows, lines=lines)


def read_user_csv(path: str | os.PathLike[str], *, what: str, max_bytes: int = DEFAULT_MAX_BYTES) -> CsvTable:
    """The CSV file ``path`` (:func:`read_user_text`, then :func:`parse_user_csv`)."""
    return parse_user_csv(read_user_text(path, what=what, max_bytes=max_bytes), what=what, path=path)


# -- NumPy archives ------------------------------------------------------------------------------------------
def load_user_npz(path: str | os.PathLike[str], *, what: str, max_bytes: int = NPZ_MAX_BYTES,
                  max_unpacked: int = NPZ_MAX_UNPACKED) -> dict[str, Any]:
    """Every array of the ``.npz`` file ``path`` (no pickles), read eagerly; a truncated or corrupt
    archive, one that unpacks to more than ``max_unpacked`` bytes or holds anything but arrays is
    refused with one line."""
    import numpy as np

    p = check_regular_file(path, what=what, max_bytes=max_bytes)
    try:
        with zipfile.ZipFile(p) as zf:
            infos = zf.infolist()
            unpacked = sum(i.file_size for i in infos)
            if unpacked > max_unpacked:
                raise UserFileError(what, p, f"unpacks to {unpacked:,} bytes, over the {_size(max_unpacked)} limit")
            if not infos or any(not i.filename.endswith(".npy") for i in infos):
                raise UserFileError(what, p, "not a NumPy .npz archive (it holds other files than arrays)")
            for info in infos:
                _check_member(zf, info, what, p)
        with np.load(p, allow_pickle=False) as z:
            return {name: z[name] for name in z.files}
    except UserFileError:
        raise
    except zipfile.BadZipFile as exc:
        raise UserFileError(what, p, f"truncated or corrupt, not a readable .npz archive ({exc})") from None
    except (ValueError, OSError, EOFError, KeyError, zlib.error) as exc:
        problem = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserFileError(what, p, f"truncated or corrupt .npz archive ({problem})") from None


def _check_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, what: str, path: Path) -> None:
    """An array member's header: no pickled objects, and no more data claimed than the member holds
    (NumPy allocates the claimed shape before reading a member)."""
    import numpy as np

    with zf.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(fh)
    if dtype.hasobject:
        raise UserFileError(what, path, f"array {info.filename[:-4]!r} holds pickled objects (never loaded)")
    count = 1
    for n in shape:
        count *= int(n)
    if count * dtype.itemsize > info.file_size:
        raise UserFileError(what, path, f"truncated or corrupt .npz archive (array {info.filename[:-4]!r} claims "
                                        f"{count * dtype.itemsize:,} bytes, holds {info.file_size:,})")
