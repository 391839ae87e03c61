"""The framework's trajectory file: one ``.npz`` any simulator's :class:`Trajectory` can be written to.

Layout (format version 1): a compressed NumPy ``.npz`` (no pickles) holding

* ``header``: a JSON string: ``{"format": "invphys.trajectory", "version": 1, "fps": ...,
  "series": [{"name", "unit", "description"}, ...], "fields": [names], "extra": {JSON scalars},
  "extra_arrays": [names], "simulator": {"simulator", "version", "config"} or null}``;
* ``series_<i>_times`` / ``series_<i>_values``: the i-th series of the header's list;
* ``frame_indices``, ``positions``, ``damage``, ``labels``: particle frames, when present;
* ``field_<i>``: the i-th particle field; ``extra_<i>``: the i-th array of ``extra``.

Names live only in the header, so any series or field name is allowed. Files written before this
format (the orange-peel example's ``trajio`` files and the validate stage's last frames) still load.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.results import TimeSeries, Trajectory

FORMAT = "invphys.trajectory"
FORMAT_VERSION = 1
#: the file name ``invphys simulate`` writes in each run directory
TRAJECTORY_FILE = "trajectory.npz"


class TrajectoryFileError(InvphysError):
    """A trajectory file is missing, unreadable or of an unknown format."""


def _json_value(value: Any) -> tuple[bool, Any]:
    """(True, plain value) when ``value`` is JSON-representable, else (False, None)."""
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return True, value
    if isinstance(value, (list, tuple, dict)):
        try:
            return True, json.loads(json.dumps(value))
        except (TypeError, ValueError):
            return False, None
    return False, None


def to_bytes(traj: Trajectory, simulator: dict[str, Any] | None = None) -> bytes:
    """The ``.npz`` bytes of ``traj``; ``simulator`` (e.g. ``Simulator.describe()``) goes in the header.

    ``extra`` entries that are neither arrays nor JSON values are left out. Raises ValueError for an
    inconsistent trajectory (:meth:`Trajectory.check`).
    """
    traj.check()
    arrays: dict[str, np.ndarray] = {}
    series = []
    for i, (name, s) in enumerate(traj.series.items()):
        series.append({"name": name, "unit": s.unit, "description": s.description})
        arrays[f"series_{i}_times"] = s.times
        arrays[f"series_{i}_values"] = s.values
    for key in ("frame_indices", "positions", "damage", "labels"):
        value = getattr(traj, key)
        if value is not None:
            arrays[key] = np.asarray(value)
    for i, arr in enumerate(traj.fields.values()):
        arrays[f"field_{i}"] = np.asarray(arr)
    scalars: dict[str, Any] = {}
    extra_arrays: list[str] = []
    for key, value in traj.extra.items():
        if isinstance(value, np.ndarray):
            arrays[f"extra_{len(extra_arrays)}"] = value
            extra_arrays.append(key)
            continue
        ok, plain = _json_value(value)
        if ok:
            scalars[key] = plain
    header = {"format": FORMAT, "version": FORMAT_VERSION, "fps": traj.fps, "series": series,
              "fields": list(traj.fields), "extra": scalars, "extra_arrays": extra_arrays,
              "simulator": simulator}
    from invphys.core.atomic import json_default

    arrays["header"] = np.array(json.dumps(header, default=json_default))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)  # type: ignore[arg-type]
    return buf.getvalue()


def save_trajectory(traj: Trajectory, path: str | Path, simulator: dict[str, Any] | None = None) -> Path:
    """Write ``traj`` to ``path`` (a ``.npz`` file, or a directory that gets ``trajectory.npz``)
    atomically; returns the file's path."""
    from invphys.core.atomic import atomic_write_bytes

    path = Path(path)
    if path.is_dir():
        path = path / TRAJECTORY_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, to_bytes(traj, simulator))
    return path


def read_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a trajectory file (``{}`` for files older than the format)."""
    return load_with_header(path)[1]


def load_trajectory(path: str | Path) -> Trajectory:
    """Read a trajectory file (``path`` may be a run directory holding ``trajectory.npz``)."""
    return load_with_header(path)[0]


def load_with_header(path: str | Path, max_bytes: int | None = None) -> tuple[Trajectory, dict[str, Any]]:
    """The trajectory in a file (or a run directory's ``trajectory.npz``) and its header (``{}`` for older
    files), read by the bounded reader (:func:`invphys.core.safe_read.load_user_npz`: a regular file of at
    most ``max_bytes``, default :data:`~invphys.core.safe_read.NPZ_MAX_BYTES`, no pickles). A truncated,
    corrupt or inconsistent file is a :class:`TrajectoryFileError` naming it."""
    from invphys.core import safe_read

    path = _resolve(path)
    try:
        data = safe_read.load_user_npz(path, what="trajectory", max_bytes=max_bytes or safe_read.NPZ_MAX_BYTES)
    except safe_read.UserFileError as exc:
        raise TrajectoryFileError(f"{path} is not a trajectory file: {exc.problem}") from None
    try:
        if "header" in data:
            header = safe_read.loads_user_json(str(data["header"]), source="its header")
            if not isinstance(header, dict):
                raise TrajectoryFileError(f"{path} is not a trajectory file: its header is not a JSON object")
            return _load_v1(data, header, path).check(), header
        return _load_legacy(data).check(), {}
    except TrajectoryFileError:
        raise
    except (InvphysError, KeyError, ValueError, TypeError, AttributeError, IndexError) as exc:
        problem = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise TrajectoryFileError(f"{path} is not a trajectory file: {problem}") from None


def _resolve(path: str | Path) -> Path:
    path = Path(path)
    if path.is_dir():
        path = path / TRAJECTORY_FILE
    if not path.exists() and not path.is_symlink():
        raise TrajectoryFileError(f"no trajectory at {path} (expected a run directory or a .npz file)")
    return path


def _load_v1(data: dict[str, Any], header: dict[str, Any], path: Path) -> Trajectory:
    if header.get("format") != FORMAT:
        raise TrajectoryFileError(f"{path}: unknown trajectory format {header.get('format')!r}")
    if int(header.get("version", 0)) > FORMAT_VERSION:
        raise TrajectoryFileError(f"{path}: trajectory format version {header['version']} is newer than this "
                                  f"invphys reads ({FORMAT_VERSION}); upgrade invphys")
    series = {s["name"]: TimeSeries(times=data[f"series_{i}_times"], values=data[f"series_{i}_values"],
                                    unit=s.get("unit", ""), description=s.get("description", ""))
              for i, s in enumerate(header["series"])}
    extra: dict[str, Any] = dict(header.get("extra", {}))
    extra.update({name: data[f"extra_{i}"] for i, name in enumerate(header.get("extra_arrays", []))})
    opt = {k: data.get(k) for k in ("frame_indices", "positions", "damage", "labels")}
    return Trajectory(series=series, fields={n: data[f"field_{i}"] for i, n in enumerate(header["fields"])},
                      fps=header.get("fps"), extra=extra, **opt)


def _load_legacy(data: dict[str, Any]) -> Trajectory:
    """Files older than the format: the orange peel's ``trajio`` and the validate stage's last frames."""
    if "frame" in data:  # one last frame: positions (N, 3), damage (N,)
        return Trajectory(positions=data["positions"][None], damage=data["damage"][None], labels=data["labels"],
                          frame_indices=np.array([int(data["frame"])]), fps=float(data["fps"]))
    from invphys.core.safe_read import loads_user_json

    extra: dict[str, Any] = dict(loads_user_json(str(data["extra_json"]), source="its extra_json")
                                 if "extra_json" in data else {})
    for key in data:
        if key.startswith("extra_") and key != "extra_json":
            extra[key[len("extra_"):]] = data[key]
    return Trajectory(positions=data["positions"], damage=data["damage"], labels=data["labels"],
                      frame_indices=data["frame_indices"], fps=float(data["fps"]), extra=extra)
