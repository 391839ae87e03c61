"""A user's own targets: feature mappings or files (JSON, YAML, CSV) checked against a feature list.

Used by the spec's ``targets: {values: [...]}`` / ``targets: {file: ...}`` and by ``invphys invert
--target FILE``. A target is a mapping ``{feature_name: value}``; every check fails with one line:
unknown names (with a did-you-mean), missing features (unless ``partial``), non-numeric or non-finite
values, unreadable files.

File shapes accepted (JSON and YAML alike)::

    {final_separation: -1.9, ...}                       # one target
    [{final_separation: -1.9, ...}, {...}]              # several
    {targets: [{id: firm, final_separation: -1.9, ...}]}  # several, with labels

A CSV file has a header of feature names (and optionally an ``id`` column) and one target per row;
an empty cell is a missing feature.

Observation noise: a target may give a standard deviation per feature, as a column (CSV) or key
``<feature>_std``, as ``{feature: {value: v, std: s}}``, or as a ``std: {feature: s, ...}`` mapping
beside the values. A std is a finite number >= 0 (0: exact) given only with its feature's value;
:attr:`UserTargets.std` holds them (NaN where none was given). Files are read by :mod:`invphys.core.safe_read`: a UTF-8 BOM (as
spreadsheets save) is accepted; a key or column given twice is refused naming both places.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError, did_you_mean

#: keys of a target mapping that label it instead of naming a feature
LABEL_KEYS: tuple[str, ...] = ("id", "name", "label")
FILE_TYPES: tuple[str, ...] = (".json", ".yaml", ".yml", ".csv")


class TargetError(InvphysError, ValueError):
    """A target is malformed: unknown or missing features, bad values, an unreadable file."""


@dataclass
class UserTargets:
    """Targets as arrays in a feature order.

    ``values`` (N, M) holds NaN where a feature is missing; ``mask`` (N, M) is True where given;
    ``labels`` names each target (its ``id``, or ``t0``, ``t1``, ...); ``std`` (N, M): the observation
    noise per feature (a standard deviation; NaN where none was given), or None when no target gives one.
    """

    values: np.ndarray
    mask: np.ndarray
    labels: list[str]
    feature_names: tuple[str, ...]
    std: np.ndarray | None = None

    def take(self, rows: np.ndarray) -> UserTargets:
        """The targets ``rows`` (indices, in that order)."""
        return replace(self, values=self.values[rows], mask=self.mask[rows], labels=[self.labels[i] for i in rows],
                       std=None if self.std is None else self.std[rows])

    def __len__(self) -> int:
        return int(self.values.shape[0])

    @property
    def complete(self) -> bool:
        return bool(self.mask.all())

    def noisy(self) -> np.ndarray:
        """(N,) True for a target that gives a std > 0 for at least one feature."""
        if self.std is None:
            return np.zeros(len(self), dtype=bool)
        return np.asarray(np.nan_to_num(self.std, nan=0.0).max(axis=1) > 0)


def _number(value: Any, feature: str, where: str) -> float:
    if isinstance(value, bool) or value is None:
        raise TargetError(f"{where}: {feature} = {value!r} is not a number")
    if isinstance(value, str):
        try:
            value = float(value.strip())
        except ValueError:
            raise TargetError(f"{where}: {feature} = {value!r} is not a number") from None
    try:
        x = float(value)
    except OverflowError:
        raise TargetError(f"{where}: {feature} is an integer too large for a number (at most ~1e308)") from None
    except (TypeError, ValueError):
        raise TargetError(f"{where}: {feature} = {value!r} is not a number") from None
    if not math.isfinite(x):
        raise TargetError(f"{where}: {feature} = {x} is not finite")
    return x


def from_mappings(rows: Sequence[Mapping[str, Any]], feature_names: Sequence[str], partial: bool = False,
                  source: str = "target") -> UserTargets:
    """Check ``rows`` (one mapping per target) against ``feature_names``; see :class:`UserTargets`."""
    names = tuple(feature_names)
    index = {n: j for j, n in enumerate(names)}
    if not rows:
        raise TargetError(f"{source}: no targets given")
    values = np.full((len(rows), len(names)), np.nan)
    std = np.full(values.shape, np.nan)
    labels: list[str] = []
    for i, row in enumerate(rows):
        where = source if len(rows) == 1 else f"{source} #{i + 1}"
        if not isinstance(row, Mapping):
            raise TargetError(f"{where}: a target is a mapping of feature name to value, got "
                              f"{type(row).__name__}")
        label = next((str(row[k]) for k in LABEL_KEYS if k in row and k not in index), f"t{i}")
        labels.append(label)
        row, noise = _split_noise(row, index, where)
        unknown = [str(k) for k in row if k not in index and k not in LABEL_KEYS]
        if unknown:
            hints = "; ".join(f"{u!r}.{did_you_mean(u, names)}" for u in unknown)
            raise TargetError(f"{where}: unknown feature {hints} Features: {', '.join(names)}")
        for key, value in row.items():
            if key in index and not _blank(value):
                values[i, index[key]] = _number(value, str(key), where)
        for key, value in noise.items():
            if np.isnan(values[i, index[key]]):
                raise TargetError(f"{where}: a std for {key} without its value")
            std[i, index[key]] = _std(value, key, where)
        missing = [n for n, j in index.items() if np.isnan(values[i, j])]
        if missing and not partial:
            raise TargetError(f"{where}: missing feature(s) {', '.join(missing)} (give all {len(names)}, "
                              f"or allow partial targets: they are left out of R)")
        if len(missing) == len(names):
            raise TargetError(f"{where}: no feature values given")
    return UserTargets(values=values, mask=np.isfinite(values), labels=labels, feature_names=names,
                       std=std if np.isfinite(std).any() else None)


def _blank(value: Any) -> bool:
    return value is None or (isinstance(value, str) and not value.strip())


def _std(value: Any, feature: str, where: str) -> float:
    """A standard deviation: a finite number >= 0."""
    if isinstance(value, str) and value.strip().lower() == "nan":
        raise TargetError(f"{where}: std of {feature} = {value!r} is not a number >= 0")
    x = _number(value, f"std of {feature}", where)
    if x < 0:
        raise TargetError(f"{where}: std of {feature} = {x:g} is negative (a standard deviation is >= 0)")
    return x


def _split_noise(row: Mapping[str, Any], index: Mapping[str, int], where: str
                 ) -> tuple[dict[str, Any], dict[str, Any]]:
    """(values by key, std by feature) of one row: ``{f: {value, std}}``, ``f_std`` keys and a ``std:``
    mapping become stds; a std given twice for one feature is refused."""
    values: dict[str, Any] = {}
    noise: dict[str, Any] = {}

    def put(feature: str, value: Any) -> None:
        if feature in noise:
            raise TargetError(f"{where}: the std of {feature} is given twice")
        if not _blank(value):
            noise[feature] = value

    for key, value in row.items():
        if key in index and isinstance(value, Mapping):
            extra = sorted(set(map(str, value)) - {"value", "std"})
            if extra or "value" not in value:
                raise TargetError(f"{where}: {key} as a mapping takes value (and std), got keys "
                                  f"{', '.join(map(str, value)) or 'none'}")
            values[key] = value["value"]
            if "std" in value:
                put(key, value["std"])
        elif key == "std" and key not in index and isinstance(value, Mapping):
            for name, s in value.items():
                if name not in index:
                    raise TargetError(f"{where}: std of unknown feature {str(name)!r}.{did_you_mean(str(name), index)}")
                put(str(name), s)
        elif isinstance(key, str) and key.endswith("_std") and key not in index and key[:-4] in index:
            put(key[:-4], value)
        else:
            values[key] = value
    return values, noise


def from_array(values: Any, feature_names: Sequence[str], source: str = "target", std: Any = None) -> UserTargets:
    """Targets given as an array (M,) or (N, M) in the order of ``feature_names``; ``std``: their
    observation noise, an array of the same shape (or (M,) for every target), finite and >= 0."""
    names = tuple(feature_names)
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise TargetError(f"{source}: not a numeric array") from None
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != len(names):
        raise TargetError(f"{source}: expected {len(names)} feature values ({', '.join(names)}), got shape "
                          f"{np.shape(values)}")
    bad = np.argwhere(~np.isfinite(arr))
    if len(bad):
        i, j = bad[0]
        raise TargetError(f"{source}: {names[j]} = {arr[i, j]} is not finite")
    return UserTargets(values=arr.copy(), mask=np.ones(arr.shape, dtype=bool),
                       labels=[f"t{i}" for i in range(len(arr))], feature_names=names,
                       std=None if std is None else _std_array(std, arr.shape, names, source))


def _std_array(std: Any, shape: tuple[int, ...], names: tuple[str, ...], source: str) -> np.ndarray:
    try:
        s = np.array(np.broadcast_to(np.asarray(std, dtype=np.float64), shape))
    except (TypeError, ValueError):
        raise TargetError(f"{source}: std must be numbers of shape {shape} (or one per feature)") from None
    bad = np.argwhere(~(np.isfinite(s) & (s >= 0)))
    if len(bad):
        i, j = bad[0]
        raise TargetError(f"{source}: std of {names[j]} = {s[i, j]} is not a finite number >= 0")
    return s


def _rows_of(data: Any, source: str) -> list[Any]:
    if data is None:
        raise TargetError(f"{source}: empty file (no targets)")
    if isinstance(data, Mapping) and "targets" in data:
        data = data["targets"]
    if isinstance(data, Mapping):
        return [data]
    if isinstance(data, list):
        return data
    raise TargetError(f"{source}: expected a mapping of feature values, a list of them, or "
                      f"{{targets: [...]}}; got {type(data).__name__}")


def require_exact(user: UserTargets, source: str) -> UserTargets:
    """``user`` unchanged when no target gives a standard deviation; otherwise one :class:`TargetError`: an
    experiment's invert stage answers exact targets, noisy ones are for ``invphys invert`` (posterior methods)."""
    if user.std is not None and bool(np.any(np.nan_to_num(user.std) > 0)):
        raise TargetError(f"{source}: gives a standard deviation per feature (a noisy observation); an experiment "
                          "spec's targets are exact values: drop the std, or answer the noisy targets with "
                          "`invphys invert BUNDLE --target FILE` (its posterior methods use the noise)")
    return user


def read_target_file(path: str | Path, feature_names: Sequence[str], partial: bool = False,
                     max_bytes: int | None = None) -> UserTargets:
    """Targets from a JSON, YAML or CSV file (see the module docstring for the shapes), read by the
    bounded reader :mod:`invphys.core.safe_read` (regular files of at most ``max_bytes``, default
    :data:`~invphys.core.safe_read.DEFAULT_MAX_BYTES`, YAML :data:`~invphys.core.safe_read.YAML_MAX_BYTES`;
    a UTF-8 BOM accepted; duplicate keys or columns and integers too large for a float refused)."""
    from invphys.core import safe_read

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in FILE_TYPES:
        raise TargetError(f"target file {str(p)!r}: unsupported type {suffix or '(none)'!r}; use "
                          f"{', '.join(FILE_TYPES)}")
    source = p.name
    try:
        if suffix == ".csv":
            table = safe_read.read_user_csv(p, what="target file", max_bytes=max_bytes or safe_read.DEFAULT_MAX_BYTES)
            return from_mappings(_csv_rows(table, source), feature_names, partial, source)
        if suffix == ".json":
            data = safe_read.load_user_json(p, what="target file", max_bytes=max_bytes or safe_read.DEFAULT_MAX_BYTES)
        else:
            data = safe_read.load_user_yaml(p, what="target file", max_bytes=max_bytes or safe_read.YAML_MAX_BYTES)
    except safe_read.UserFileError as exc:
        raise TargetError(str(exc)) from None
    return from_mappings(_rows_of(data, source), feature_names, partial, source)


def _csv_rows(table: Any, source: str) -> list[dict[str, str]]:
    """The rows of a :class:`~invphys.core.safe_read.CsvTable` as mappings of its header's names."""
    rows = []
    width = len(table.header)
    for row, n in zip(table.rows, table.lines, strict=True):
        if len(row) > width:
            raise TargetError(f"{source} line {n}: more values than header columns")
        if len(row) < width:
            raise TargetError(f"{source} line {n}: fewer values than header columns")
        rows.append(dict(zip(table.header, row, strict=True)))
    return rows


def parse_assignments(items: Sequence[str], feature_names: Sequence[str], partial: bool = False,
                      source: str = "--feature") -> UserTargets:
    """One target from ``name=value`` strings (the CLI's repeatable ``--feature``)."""
    row: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise TargetError(f"{source} {item!r}: expected name=value")
        if name in row:
            raise TargetError(f"{source}: {name} is given twice")
        if not value.strip():
            raise TargetError(f"{source} {item!r}: no value after '='")
        row[name] = value
    return from_mappings([row], feature_names, partial, source)
