"""The bundle manifest (``manifest.yaml``): what a bundle holds, who made it, and the checks on load.

Load order (:func:`read_manifest`): the manifest parses -> ``format_version`` (newer: "upgrade invphys";
older: named migrations) -> every file listed under ``files`` exists and has its sha256. Unknown keys
are kept, so a manifest written by a newer minor version still loads. Simulator and feature checks
against the installed plugins happen in :mod:`invphys.inverter.bundle`.
"""

from __future__ import annotations

import hashlib
import platform
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from invphys.core.errors import InvphysError

MANIFEST_FILE = "manifest.yaml"
FORMAT_VERSION = 1
#: format_version -> function upgrading a manifest dict of that version to the next one
MIGRATIONS: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {}
REQUIRED = ("format_version", "parameter_space", "features", "simulator", "components", "methods", "files")


class BundleError(InvphysError):
    """An inverter bundle is missing, incomplete, changed, or incompatible with this installation."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def sha256_json(obj: Any) -> str:
    import json

    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def system_info() -> dict[str, str]:
    """Versions of Python and the libraries a bundle's parts depend on (recorded, compared on load)."""
    from importlib import metadata

    info = {"python": platform.python_version(), "platform": platform.platform(terse=True)}
    for dist in ("invphys", "numpy", "torch", "stable-baselines3"):
        try:
            info[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    return info


def file_hashes(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` except the manifest, by POSIX relative path."""
    return {p.relative_to(root).as_posix(): sha256_file(p) for p in sorted(root.rglob("*"))
            if p.is_file() and p.name != MANIFEST_FILE}


def write_manifest(root: Path, manifest: dict[str, Any]) -> Path:
    """Hash the bundle's files into ``manifest['files']`` and write ``manifest.yaml`` atomically."""
    import yaml

    from invphys.core.atomic import atomic_write_bytes

    manifest = {**manifest, "files": file_hashes(root)}
    text = yaml.safe_dump(manifest, sort_keys=False, allow_unicode=True, width=110)
    atomic_write_bytes(root / MANIFEST_FILE, text.encode())
    return root / MANIFEST_FILE


def read_manifest(root: str | Path, verify: bool = True) -> dict[str, Any]:
    """The manifest of the bundle at ``root``, migrated to :data:`FORMAT_VERSION` and file-checked."""
    import yaml

    root = Path(root)
    if not root.exists():
        raise BundleError(f"no inverter bundle at {str(root)!r} (no such directory)")
    if not root.is_dir():
        raise BundleError(f"{str(root)!r} is a file, not an inverter bundle directory")
    path = root / MANIFEST_FILE
    if not path.is_file():
        hint = " (a run directory? its bundle is in inverter/)" if (root / "inverter" / MANIFEST_FILE).is_file() else ""
        raise BundleError(f"{str(root)!r} is not an inverter bundle: it has no {MANIFEST_FILE}{hint}")
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise BundleError(f"{path}: the manifest is not valid YAML ({type(exc).__name__})") from None
    if not isinstance(data, dict):
        raise BundleError(f"{path}: the manifest is not a mapping")
    version = data.get("format_version")
    if not isinstance(version, int):
        raise BundleError(f"{path}: no integer format_version; not an invphys inverter bundle")
    if version > FORMAT_VERSION:
        made = data.get("invphys_version", "a newer invphys")
        raise BundleError(f"bundle {str(root)!r} has format {version} (made by invphys {made}); this invphys "
                          f"reads format {FORMAT_VERSION}: upgrade invphys")
    while version < FORMAT_VERSION:
        if version not in MIGRATIONS:
            raise BundleError(f"bundle {str(root)!r} has format {version}, which this invphys cannot migrate; "
                              f"re-export it with a matching invphys")
        data = MIGRATIONS[version](data)
        version = data["format_version"]
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise BundleError(f"{path}: the manifest lacks {', '.join(missing)}")
    if verify:
        for rel, digest in (data.get("files") or {}).items():
            f = root / rel
            if not f.is_file():
                raise BundleError(f"bundle {str(root)!r} is missing part {rel}")
            if sha256_file(f) != digest:
                raise BundleError(f"bundle {str(root)!r}: {rel} has changed since the bundle was written "
                                  f"(sha256 mismatch); re-export the bundle")
    return data


def python_mismatch(info: dict[str, Any]) -> str | None:
    """A warning when the bundle was written under another Python major.minor (like MLflow)."""
    saved = str(info.get("python", ""))
    now = f"{sys.version_info.major}.{sys.version_info.minor}"
    if saved and not saved.startswith(now + ".") and saved != now:
        return f"bundle written with Python {saved}, running {platform.python_version()}"
    return None
