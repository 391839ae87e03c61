"""The bundle manifest (``manifest.yaml``): what a bundle holds, who made it, and the checks on load.

Load order (:func:`read_manifest`): the manifest parses -> ``format_version`` (newer: "upgrade invphys";
older: named migrations) -> every file listed under ``files`` exists and has its sha256. Unknown keys
are kept, so a manifest written by a newer minor version still loads. Simulator and feature checks
against the installed plugins happen in :mod:`invphys.inverter.bundle`.

What loading may touch: only files inside the bundle directory that the manifest lists under ``files``
(:func:`part_path` refuses ``..``, absolute paths and symlinks that leave the bundle), read as JSON,
YAML, NumPy ``.npz`` without pickles or torch tensors with ``weights_only=True``. Format 2 holds no
pickled part; a format-1 bundle that still holds one (:data:`LEGACY_PICKLES`) is refused with the command
that converts it (:data:`UPGRADE_HINT`).
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import Any

from invphys.core.errors import InvphysError

MANIFEST_FILE = "manifest.yaml"
#: 3: method entries may carry keys that change the answer (``uncertainty_penalty``, ``start``), which a format-2
#: reader would ignore and answer differently; 2: no pickled parts (NPE flows and PPO policies as tensors);
#: 1: npe.pt and policy.zip were pickles. A bundle is written in the lowest format that holds it
#: (:func:`required_format`), so older readers keep reading bundles without those keys.
FORMAT_VERSION = 3
#: method-entry keys a format-2 reader does not know and would silently ignore
FORMAT_3_METHOD_KEYS = ("uncertainty_penalty", "start")
REQUIRED = ("format_version", "parameter_space", "features", "simulator", "components", "methods", "files")
#: sub-keys every manifest needs (dotted), checked before anything else reads them
REQUIRED_KEYS = ("parameter_space.names", "parameter_space.low", "parameter_space.high",
                 "parameter_space.log_scale", "parameter_space.units", "features.names", "features.scales",
                 "simulator.name", "components.surrogate", "components.surrogate.type", "components.surrogate.path")
#: largest bundle part hashed or read (bytes)
PART_MAX_BYTES = 2 << 30
#: parts of format-1 bundles that only unpickling (running code stored in the file) could load
LEGACY_PICKLES = ("npe.pt", "policy.zip")
UPGRADE_HINT = ("if you trust where it came from, convert it once (this runs the pickled code): "
                "invphys export --upgrade {root} --out NEW_DIR --trust-pickles")


def _migrate_1(data: dict[str, Any]) -> dict[str, Any]:
    """1 -> 2: the layout is the same; pickled parts (refused by :func:`legacy_pickles`) need --upgrade."""
    return {**data, "format_version": 2}


def _migrate_2(data: dict[str, Any]) -> dict[str, Any]:
    """2 -> 3: format 3 only adds method keys (:data:`FORMAT_3_METHOD_KEYS`)."""
    return {**data, "format_version": 3}


#: format_version -> function upgrading a manifest dict of that version to the next one
MIGRATIONS: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {1: _migrate_1, 2: _migrate_2}


def required_format(manifest: dict[str, Any]) -> int:
    """The lowest format that holds ``manifest``: 3 when a method entry uses a key of
    :data:`FORMAT_3_METHOD_KEYS` (an older invphys would answer that method differently without a word), else 2."""
    methods = manifest.get("methods") or {}
    uses = any(isinstance(e, dict) and any(k in e for k in FORMAT_3_METHOD_KEYS) for e in methods.values())
    return 3 if uses else 2


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
    """sha256 of every file under ``root`` except the manifest, by POSIX relative path (a symlink or
    another non-regular file in the bundle is refused: a bundle holds plain files only)."""
    out: dict[str, str] = {}
    for p in sorted(root.rglob("*")):
        if p.is_symlink() or not (p.is_dir() or p.is_file()):
            raise BundleError(f"{p}: not a plain file or directory; a bundle holds plain files only")
        if p.is_file() and p.relative_to(root).as_posix() != MANIFEST_FILE:
            out[p.relative_to(root).as_posix()] = sha256_file(p)
    return out


def write_manifest(root: Path, manifest: dict[str, Any]) -> Path:
    """Hash the bundle's files into ``manifest['files']`` and write ``manifest.yaml`` atomically, in the
    lowest format that holds it (:func:`required_format`)."""
    import yaml

    from invphys.core.atomic import atomic_write_bytes

    manifest = {**manifest, "format_version": required_format(manifest), "files": file_hashes(root)}
    text = yaml.safe_dump(manifest, sort_keys=False, allow_unicode=True, width=110)
    atomic_write_bytes(root / MANIFEST_FILE, text.encode())
    return root / MANIFEST_FILE


def read_manifest(root: str | Path, verify: bool = True, allow_legacy: bool = False) -> dict[str, Any]:
    """The manifest of the bundle at ``root``, migrated to :data:`FORMAT_VERSION` and checked: required
    keys, every listed file inside the bundle, no pickled part (unless ``allow_legacy``: the upgrade
    only), and with ``verify`` every file's sha256."""
    from invphys.core.safe_read import check_regular_file

    root = Path(root)
    if not root.exists():
        raise BundleError(f"no inverter bundle at {str(root)!r} (no such directory)")
    if not root.is_dir():
        raise BundleError(f"{str(root)!r} is a file, not an inverter bundle directory")
    path = root / MANIFEST_FILE
    if not path.is_file():
        hint = " (a run directory? its bundle is in inverter/)" if (root / "inverter" / MANIFEST_FILE).is_file() else ""
        raise BundleError(f"{str(root)!r} is not an inverter bundle: it has no {MANIFEST_FILE}{hint}")
    data = _parse(path)
    version = data.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool):
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
    check_keys(data, path)
    files = data["files"]
    for rel in files:
        part_path(root, rel, f"files entry {rel!r}")
    legacy = [rel for rel in files if PurePosixPath(rel).name in LEGACY_PICKLES]
    if legacy and not allow_legacy:
        raise BundleError(f"bundle {str(root)!r} holds {legacy[0]}, a pickled part written by an older invphys: "
                          f"loading it would run code stored in the file, so it is refused; "
                          + UPGRADE_HINT.format(root=str(root)))
    if verify:
        for rel, digest in files.items():
            f = root / rel
            if not os.path.lexists(f):
                raise BundleError(f"bundle {str(root)!r} is missing part {rel}")
            try:
                check_regular_file(f, what=f"bundle part {rel}", max_bytes=PART_MAX_BYTES)
            except InvphysError as exc:
                raise BundleError(f"bundle {str(root)!r}: {exc}") from None
            if sha256_file(f) != digest:
                raise BundleError(f"bundle {str(root)!r}: {rel} has changed since the bundle was written "
                                  f"(sha256 mismatch); re-export the bundle")
    for rel in files:
        if PurePosixPath(rel).name not in LEGACY_PICKLES and os.path.isfile(root / rel):
            problem = pickle_problem(root / rel)
            if problem:
                raise BundleError(f"bundle {str(root)!r}: {rel} {problem}; refusing to load the bundle")
    return data


def _parse(path: Path) -> dict[str, Any]:
    """The manifest's YAML as a mapping, read by the bounded reader (a regular file, size, alias, depth and
    duplicate-key limits); every failure is a BundleError naming the file."""
    from invphys.core.safe_read import load_user_yaml

    try:
        data = load_user_yaml(path, what="bundle manifest")
    except InvphysError as exc:
        raise BundleError(str(exc)) from None
    if not isinstance(data, dict):
        raise BundleError(f"{path}: the manifest is not a mapping")
    return data


#: the only globals a torch state dict's pickle names (tensors rebuilt from storages, the dict itself)
TORCH_GLOBALS = ("collections OrderedDict", "torch._utils _rebuild_tensor_v2", "torch._utils _rebuild_parameter")
#: pickle opcodes that build objects by other means than GLOBAL + REDUCE (never in a torch state dict)
FOREIGN_OPCODES = ("STACK_GLOBAL", "INST", "OBJ", "NEWOBJ", "NEWOBJ_EX", "EXT1", "EXT2", "EXT4")


def pickle_problem(path: Path) -> str | None:
    """Why the weight file ``path`` could run code when loaded (None: it cannot), read without loading it:
    a ``.npz`` must hold only ``.npy`` arrays without objects; a ``.pt``/``.pth`` must be a torch zip whose
    pickle names only tensors, storages and an ordered dict (scanned with :mod:`pickletools`, which runs
    nothing). Other files are not loaded as pickles by invphys and pass."""
    import zipfile

    suffix = path.suffix.lower()
    if suffix not in (".npz", ".npy", ".pt", ".pth", ".pkl", ".pickle"):
        return None
    if suffix in (".pkl", ".pickle"):
        return "is a pickle"
    try:
        if suffix == ".npy":
            with open(path, "rb") as fh:
                return _npy_problem(fh, path.name)
        with zipfile.ZipFile(path) as zf:
            if suffix == ".npz":
                for name in zf.namelist():
                    if not name.endswith(".npy"):
                        return f"holds {name!r}, not a NumPy array"
                    with zf.open(name) as fh:
                        problem = _npy_problem(fh, name)
                    if problem:
                        return problem
                return None
            pkl = [n for n in zf.namelist() if n.endswith("data.pkl")]
            if len(pkl) != 1:
                return "is not a torch weights archive (no single data.pkl)"
            return _torch_pickle_problem(zf.read(pkl[0]))
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        what = "NumPy archive" if suffix in (".npz", ".npy") else "torch weights archive"
        return f"is not a {what} ({type(exc).__name__}: it may be a pickle, which invphys never loads)"


def _npy_problem(fh: Any, name: str) -> str | None:
    import numpy as np

    version = np.lib.format.read_magic(fh)
    header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    _, _, dtype = header(fh)
    return f"holds array {name!r} of Python objects (a pickle)" if dtype.hasobject else None


def _torch_pickle_problem(data: bytes) -> str | None:
    import pickletools
    import re

    for op, arg, _ in pickletools.genops(data):
        if op.name in FOREIGN_OPCODES:
            return f"holds pickled code (opcode {op.name}), not plain tensors"
        if op.name == "GLOBAL" and arg not in TORCH_GLOBALS and not re.fullmatch(r"torch [A-Za-z0-9]*Storage", str(arg)):
            return f"holds pickled code (a reference to {str(arg).replace(' ', '.')}), not plain tensors"
    return None


def check_keys(data: dict[str, Any], path: Path) -> None:
    """Refuse a manifest without a required sub-key or with one of the wrong shape, naming the key."""
    for dotted in REQUIRED_KEYS:
        node: Any = data
        for i, key in enumerate(dotted.split(".")):
            if not isinstance(node, dict):
                raise BundleError(f"{path}: {'.'.join(dotted.split('.')[:i])} is not a mapping")
            if key not in node:
                raise BundleError(f"{path}: the manifest lacks {dotted}")
            node = node[key]
    ps = data["parameter_space"]
    for key in ("names", "low", "high", "log_scale", "units"):
        if not isinstance(ps[key], list) or len(ps[key]) != len(ps["names"]) or not ps["names"]:
            raise BundleError(f"{path}: parameter_space.{key} must be a list with one entry per parameter")
    names = data["features"]["names"]
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise BundleError(f"{path}: features.names must be a non-empty list of feature names")
    if not isinstance(data["files"], dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                       for k, v in data["files"].items()):
        raise BundleError(f"{path}: files must map relative paths to sha256 digests")
    if not isinstance(data["methods"], dict):
        raise BundleError(f"{path}: methods must be a mapping of method labels to entries")
    for label, entry in data["methods"].items():
        for key in ("type", "kind", "space"):
            if not isinstance(entry, dict) or not isinstance(entry.get(key), str):
                raise BundleError(f"{path}: the manifest lacks methods.{label}.{key}")
        if not isinstance(entry.get("evaluator", "shared"), str):
            raise BundleError(f"{path}: methods.{label}.evaluator must be a name")
    for dotted in ("simulator.name", "components.surrogate.type"):
        section, key = dotted.split(".", 1)
        node = data[section][key] if section != "components" else data["components"]["surrogate"]["type"]
        if not isinstance(node, str) or not node:
            raise BundleError(f"{path}: {dotted} must be a name")
    for dotted, node in (("features.extractor", data["features"].get("extractor")),
                         ("system_info", data.get("system_info"))):
        if node is not None and not isinstance(node, dict):
            raise BundleError(f"{path}: {dotted} must be a mapping")
    _check_types(data, path)
    default = data.get("default_method")
    if default is not None and (not isinstance(default, str) or default not in data["methods"]):
        raise BundleError(f"{path}: default_method {default!r} names no method of the bundle")
    if not isinstance(data["components"].get("latents") or {}, dict):
        raise BundleError(f"{path}: components.latents must be a mapping")


def unimported_code_path(name: Any) -> str | None:
    """The module a ``module:Class`` plugin name would import, when that module is not imported yet (None
    for a registered plugin name, or a module the process already imported). A bundle naming such a path
    would run that module's code on load: :func:`check_keys` refuses it for components and methods, and
    the simulator and extractor checks skip it."""
    if not isinstance(name, str) or ":" not in name:
        return None
    module = name.split(":", 1)[0]
    return None if module in sys.modules else module


def _check_types(data: dict[str, Any], path: Path) -> None:
    comps = data["components"]
    named = [("components.surrogate.type", comps["surrogate"].get("type"))]
    named += [(f"components.latents.{k}.type", v.get("type")) for k, v in (comps.get("latents") or {}).items()
              if isinstance(v, dict)]
    named += [(f"methods.{k}.type", v.get("type")) for k, v in data["methods"].items()]
    for dotted, name in named:
        module = unimported_code_path(name)
        if module:
            raise BundleError(f"{path}: {dotted} = {name!r} is a module path: loading it would import and run "
                              f"{module}; a bundle may name only installed plugins")


def part_path(root: Path, rel: Any, what: str) -> Path:
    """``root / rel`` for a relative POSIX path that stays inside the bundle (no absolute path, no ``..``,
    no symlink leading out); anything else is a BundleError naming ``what``."""
    if not isinstance(rel, str) or not rel or "\\" in rel or "\0" in rel:
        raise BundleError(f"bundle {str(root)!r}: {what} is not a relative path inside the bundle ({rel!r})")
    pure = PurePosixPath(rel)
    if pure.is_absolute() or ".." in pure.parts or rel.startswith("~"):
        raise BundleError(f"bundle {str(root)!r}: {what} = {rel!r} points outside the bundle "
                          f"(absolute paths and '..' are refused)")
    full = root / pure
    base = os.path.realpath(root)
    if os.path.commonpath([os.path.realpath(full), base]) != base:
        raise BundleError(f"bundle {str(root)!r}: {what} = {rel!r} leads outside the bundle through a symlink")
    return full


def check_covered(root: Path, rel: str, files: dict[str, str], what: str) -> Path:
    """The file or directory ``rel`` of the bundle, every file of which is listed (and so hashed) in the
    manifest's ``files``: a BundleError names an unlisted file or a symlink inside it."""
    full = part_path(root, rel, what)
    if full.is_symlink():
        raise BundleError(f"bundle {str(root)!r}: {what} = {rel!r} is a symlink; a bundle holds plain files only")
    if full.is_file():
        if rel not in files and PurePosixPath(rel).as_posix() not in files:
            raise BundleError(f"bundle {str(root)!r}: {rel} ({what}) is not listed in the manifest's files, "
                              f"so nothing checks it; refusing to load it")
        return full
    if not full.is_dir():
        raise BundleError(f"bundle {str(root)!r} is missing part {rel} ({what})")
    for dirpath, dirnames, filenames in os.walk(full):
        for name in sorted(dirnames + filenames):
            p = Path(dirpath) / name
            sub = p.relative_to(root).as_posix()
            if p.is_symlink():
                raise BundleError(f"bundle {str(root)!r}: {sub} is a symlink; a bundle holds plain files only")
            if name in filenames and sub not in files:
                raise BundleError(f"bundle {str(root)!r}: {sub} is not listed in the manifest's files, so nothing "
                                  f"checks it; refusing to load {what}")
    return full


def python_mismatch(info: dict[str, Any]) -> str | None:
    """A warning when the bundle was written under another Python major.minor (like MLflow)."""
    saved = str(info.get("python", ""))
    now = f"{sys.version_info.major}.{sys.version_info.minor}"
    if saved and not saved.startswith(now + ".") and saved != now:
        return f"bundle written with Python {saved}, running {platform.python_version()}"
    return None
