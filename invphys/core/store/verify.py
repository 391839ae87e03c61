"""Verify and repair: check every part of a store against its manifest (nothing changed), and set bad parts
aside in ``_quarantine/`` and rebuild the manifest from what remains."""

from __future__ import annotations

import os
import uuid
from contextlib import AbstractContextManager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from invphys.core.store.base import StoreBase
from invphys.core.store.layout import (
    MANIFEST_FILE,
    QUARANTINE_DIR,
    DatasetError,
    StoreNotWritableError,
    UnsafeStoreError,
    metadata_problem,
    not_writable,
    short,
)
from invphys.core.store.scan import PartProblem, part_entry, scan_store


@dataclass
class VerifyReport:
    """What :meth:`DatasetStore.verify` found (JSON-ready through :meth:`to_dict`)."""

    path: str
    parts: int
    rows: int
    problems: list[PartProblem]
    has_manifest: bool = True
    actions: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and self.has_manifest

    def to_dict(self) -> dict[str, Any]:
        return {"path": self.path, "ok": self.ok, "parts": self.parts, "rows": self.rows,
                "has_manifest": self.has_manifest, "problems": [asdict(p) for p in self.problems],
                "actions": self.actions}


class Verifier(StoreBase):
    """The verify-and-repair part of :class:`~invphys.core.dataset.DatasetStore`."""

    if TYPE_CHECKING:  # the append part's write lock (invphys.core.store.append.Appender.writer)
        def writer(self) -> AbstractContextManager[Any]: ...

    def verify(self) -> VerifyReport:
        """Check every part against the manifest and the store's schema; nothing is changed. Damage is
        reported, not raised: a malformed manifest is a problem of ``_manifest.json`` (the parts are then
        checked on their own); only a path that holds no readable store raises :class:`DatasetError`."""
        try:
            scan = scan_store(self)
        except DatasetError as exc:
            if not self.manifest_path.exists() or metadata_problem(self.metadata):
                raise
            scan = scan_store(self, use_manifest=False)
            scan.problems.insert(0, PartProblem(MANIFEST_FILE, "corrupt", f"{short(exc)}"))
        return VerifyReport(path=str(self.path), parts=len(scan.parts),
                            rows=sum(p.table.num_rows for p in scan.parts), problems=scan.problems,
                            has_manifest=scan.has_manifest)

    def repair(self) -> VerifyReport:
        """Move corrupt/foreign/duplicate parts' files to ``_quarantine/``, drop missing ones from the
        manifest, adopt good unlisted parts, and rewrite the manifest from what remains. Returns the
        report, with ``actions``.

        Files move only by renaming inside the store directory: a ``_quarantine`` that is a symbolic
        link (or not a directory) raises :class:`UnsafeStoreError`, a store that cannot be written
        :class:`StoreNotWritableError`; either before anything changed. A symbolic-link part is moved
        as the link itself, never its target."""
        qdir = self.path / QUARANTINE_DIR
        _check_quarantine(qdir)
        if not self.exists:
            _ = self.metadata  # raises the reader's message (no store, or a file); nothing is created
        with self.writer():
            actions: list[str] = []
            try:
                scan = scan_store(self)
            except DatasetError:
                if not self.manifest_path.exists() or metadata_problem(self.metadata):
                    raise
                scan = scan_store(self, use_manifest=False)  # a malformed manifest: rebuilt from the parts
                actions.append("replaced the malformed manifest")
            if not scan.problems and scan.has_manifest and not actions:
                return self.verify()
            _probe_writable(self.path)
            try:
                for problem in scan.problems:
                    if problem.kind == "missing":
                        actions.append(f"dropped {problem.part} from the manifest (file missing)")
                    elif problem.kind == "unlisted":
                        actions.append(f"adopted {problem.part} into the manifest")
                    elif problem.kind == "stray":
                        actions.append(f"left {problem.part} in place (not the store's to move: move it out)")
                    else:
                        _quarantine(self.path, qdir, problem.part)
                        actions.append(f"moved {problem.part} ({problem.kind}) to {QUARANTINE_DIR}/")
                self._write_manifest([part_entry(p) for p in scan.parts])
            except OSError as exc:
                raise StoreNotWritableError(not_writable(self.path, exc, actions)) from None
            if not scan.has_manifest and not actions:
                actions.append("wrote a manifest")
            report = self.verify()
            report.actions = actions
            return report


def _check_quarantine(qdir: Path) -> None:
    """Refuse a ``_quarantine`` that is a symbolic link or not a directory (moves would leave the store)."""
    if os.path.islink(qdir):
        raise UnsafeStoreError(f"{qdir} is a symbolic link; repair moves files only inside the store: "
                               f"remove the link (or make {QUARANTINE_DIR} a directory) and repair again")
    if os.path.lexists(qdir) and not os.path.isdir(qdir):
        raise UnsafeStoreError(f"{qdir} is not a directory; move it away and repair again")


def _quarantine(store: Path, qdir: Path, name: str) -> None:
    """Rename the store's entry ``name`` (a link as the link itself) into ``qdir``, never replacing a file
    there; both directories are opened without following links, so nothing leaves the store."""
    if not os.path.lexists(qdir):
        os.mkdir(qdir)
    _check_quarantine(qdir)
    src_fd = os.open(store, os.O_RDONLY | os.O_DIRECTORY)
    try:
        dst_fd = os.open(qdir, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_NOFOLLOW", 0))
        try:
            target = name
            while os.path.lexists(qdir / target):
                target = f"{name}.{uuid.uuid4().hex[:6]}"
            os.rename(name, target, src_dir_fd=src_fd, dst_dir_fd=dst_fd)
        finally:
            os.close(dst_fd)
    finally:
        os.close(src_fd)


def _probe_writable(path: Path) -> None:
    """Raise :class:`StoreNotWritableError` unless a file can be created (and removed) in ``path``."""
    probe = path / f".part-probe-{uuid.uuid4().hex[:8]}.tmp"  # a writer clears any left behind
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        os.unlink(probe)
    except OSError as exc:
        raise StoreNotWritableError(not_writable(path, exc)) from None
