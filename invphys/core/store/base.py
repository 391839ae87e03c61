"""What every part of the dataset store shares: its directory, its metadata and its manifest."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from invphys.core.atomic import write_json
from invphys.core.store.layout import (
    MANIFEST_FILE,
    MANIFEST_FORMAT,
    METADATA_FILE,
    PART_RE,
    DatasetError,
    metadata_problem,
    read_json,
    utcnow,
)


class StoreBase:
    """A store's directory, ``_metadata.json`` and ``_manifest.json``; the append, verify-and-repair and read
    parts (:mod:`invphys.core.store.append`, ``.verify``, ``.read``) build on it."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._lock: Any = None
        self._keys: set[str] | None = None

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"

    @property
    def metadata_path(self) -> Path:
        return self.path / METADATA_FILE

    @property
    def manifest_path(self) -> Path:
        return self.path / MANIFEST_FILE

    @property
    def exists(self) -> bool:
        return self.metadata_path.is_file()

    @property
    def metadata(self) -> dict[str, Any]:
        """The parsed, shape-checked ``_metadata.json`` (:class:`DatasetError` when absent or malformed)."""
        if self.path.exists() and not self.path.is_dir():
            raise DatasetError(f"{str(self.path)!r} is a file, not a dataset directory")
        if not self.exists:
            hint = " (it has Parquet files but no _metadata.json)" if self.parts() else ""
            raise DatasetError(f"no invphys dataset at {str(self.path)!r}{hint}")
        meta = read_json(self.metadata_path)
        problem = metadata_problem(meta)
        if problem:
            raise DatasetError(f"{self.metadata_path} is malformed: {problem}")
        return meta

    def write_metadata(self, metadata: dict[str, Any]) -> None:
        """Replace ``_metadata.json`` atomically (temp file, fsync, rename)."""
        self.path.mkdir(parents=True, exist_ok=True)
        data = dict(metadata, updated_at=utcnow())
        write_json(self.metadata_path, data)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(self.metadata["param_names"])

    @property
    def feature_names(self) -> tuple[str, ...]:
        return tuple(self.metadata["feature_names"])

    @property
    def manifest(self) -> dict[str, Any] | None:
        """The parsed ``_manifest.json``, or None for a store written before manifests existed."""
        if not self.manifest_path.exists():
            return None
        data = read_json(self.manifest_path)
        parts = data.get("parts") if isinstance(data, dict) else None
        if not isinstance(parts, list) or not all(
                isinstance(p, dict) and isinstance(p.get("name"), str) and PART_RE.match(p["name"])
                and isinstance(p.get("sha256"), str) and isinstance(p.get("rows"), int) for p in parts):
            raise DatasetError(f"{self.manifest_path} is malformed; `invphys dataset verify {self.path} --repair` "
                               "rebuilds it from the parts")
        return data

    def _write_manifest(self, parts: list[dict[str, Any]]) -> None:
        write_json(self.manifest_path, {"format": MANIFEST_FORMAT, "parts": parts,
                                        "rows": int(sum(p["rows"] for p in parts)), "updated_at": utcnow()})

    def parts(self) -> list[Path]:
        """The Parquet part files present, in write order (listed or not)."""
        if not self.path.is_dir():
            return []
        return sorted(p for p in self.path.glob("part-*.parquet") if p.is_file() and not p.is_symlink())
