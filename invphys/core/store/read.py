"""Reading: a store's rows as an Arrow table, a pandas frame or arrays sorted by key, always after checking
the store against its manifest; its summary; and a cheap fingerprint of what it holds."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.store.base import StoreBase
from invphys.core.store.keys import keys_fingerprint
from invphys.core.store.layout import DatasetError, short
from invphys.core.store.rows import DatasetArrays
from invphys.core.store.scan import HARMLESS, problems_message, scan_store


class Reader(StoreBase):
    """The read part of :class:`~invphys.core.dataset.DatasetStore`."""

    def content_fingerprint(self, first_ok: int | None = None) -> str:
        """A cheap hash of what the store holds now: its manifest's checksums (or, for a store without
        a manifest, each part's name, size and modification time). Changes when rows are added or lost.

        With ``first_ok``, the hash of the store's first ``first_ok`` ok rows in store order (the rows
        :meth:`arrays` gives with the same ``first_ok``): of the parts up to the one holding the last of
        them (plus the count when that part holds more ok rows), so parts appended later leave it
        unchanged. Finding that part reads the ``status`` column of the parts before it, nothing else.
        When those parts hold exactly ``first_ok`` ok rows it equals the fingerprint the store had when
        they were all it held. Raises :class:`DatasetError` when the store holds fewer ok rows.
        """
        _check_first_ok(first_ok)
        if not self.exists:
            return "absent"
        try:
            manifest = self.manifest
        except DatasetError:
            manifest = None
        if manifest is not None:
            entries = [(str(p["name"]), f"{p['name']}:{p['sha256']}") for p in manifest["parts"]]
        else:
            entries = [(p.name, f"{p.name}:{p.stat().st_size}:{p.stat().st_mtime_ns}") for p in self.parts()]
        extra: list[str] = []
        if first_ok is not None:
            held = 0
            for i, (name, _) in enumerate(entries):
                held += self._part_ok_rows(name)
                if held >= first_ok:
                    entries = entries[:i + 1]
                    break
            else:
                raise DatasetError(_too_few_message(self.path, held, first_ok))
            extra = [] if held == first_ok else [f"first {first_ok} ok rows"]
        items = sorted(item for _, item in entries) + extra
        return hashlib.sha256("\n".join(items).encode()).hexdigest()[:16]

    def _part_ok_rows(self, name: str) -> int:
        """How many ok rows the part file ``name`` holds (its ``status`` column alone is read)."""
        import pyarrow.compute as pc
        import pyarrow.parquet as pq

        try:
            if not stat.S_ISREG(os.lstat(self.path / name).st_mode):
                raise OSError("not a regular file")
            status = pq.read_table(self.path / name, columns=["status"], use_threads=False,
                                   pre_buffer=False).column("status")
        except Exception as exc:  # missing or corrupt: the reader names it (and how to repair it)
            raise DatasetError(f"dataset {str(self.path)!r}: cannot read part {name}: {short(exc)}; "
                               f"`invphys dataset verify {self.path}` checks the store") from None
        return int(pc.sum(pc.equal(status, "ok")).as_py() or 0)

    def _table(self) -> Any:
        """Every stored row as one Arrow table, after checking the store (refuses any problem but an
        unlisted good part, whose rows are not read)."""
        scan = scan_store(self)
        bad = [p for p in scan.problems if p.kind not in HARMLESS]
        if bad:
            raise DatasetError(problems_message(self.path, bad))
        parts = [p.table for p in scan.parts if p.name not in {q.part for q in scan.problems}]
        import pyarrow as pa

        return pa.concat_tables(parts) if parts else scan.schema.empty_table()

    def keys(self) -> set[str]:
        """Keys of every stored row (ok and failed)."""
        return set(self._table().column("key").to_pylist())

    def ok_count(self) -> int:
        """How many ok rows the store holds (the store is checked first)."""
        import pyarrow.compute as pc

        return int(pc.sum(pc.equal(self._table().column("status"), "ok")).as_py() or 0)

    def frame(self, ok_only: bool = False, first_ok: int | None = None) -> Any:
        """All rows as a pandas DataFrame sorted by key (the store is checked first).

        ``first_ok``: only the rows stored up to the ``first_ok``-th ok row, in store order (parts in
        write order, rows in each part in order): the rows the store held when it held ``first_ok``
        ok rows, since stores only append. Raises :class:`DatasetError` when it holds fewer.
        """
        import pandas as pd

        _check_first_ok(first_ok)
        df: pd.DataFrame = self._table().to_pandas(use_threads=False)
        if first_ok is not None:
            ok_at = np.flatnonzero((df["status"] == "ok").to_numpy(dtype=bool))
            if len(ok_at) < first_ok:
                raise DatasetError(_too_few_message(self.path, len(ok_at), first_ok))
            df = df.iloc[:int(ok_at[first_ok - 1]) + 1]
        df = df.sort_values("key", kind="stable").reset_index(drop=True)
        if ok_only:
            df = df[df["status"] == "ok"].reset_index(drop=True)
        return df

    def arrays(self, ok_only: bool = True, first_ok: int | None = None) -> DatasetArrays:
        """The rows as :class:`DatasetArrays` (only successful runs unless ``ok_only=False``; only the
        store's first ``first_ok`` ok rows when given, see :meth:`frame`)."""
        meta = self.metadata
        pnames, fnames = tuple(meta["param_names"]), tuple(meta["feature_names"])
        df = self.frame(ok_only=ok_only, first_ok=first_ok)
        keys = df["key"].to_numpy(dtype=object)

        def block(prefix: str, names: tuple[str, ...]) -> np.ndarray:
            cols = [f"{prefix}{n}" for n in names]
            return df[cols].to_numpy(dtype=np.float64, na_value=np.nan).reshape(len(df), len(cols))

        return DatasetArrays(theta=block("theta_", pnames), y=block("f_", fnames), params=block("p_", pnames),
                             param_names=pnames, feature_names=fnames, keys=keys,
                             fingerprint=keys_fingerprint(list(keys)),
                             ok=(df["status"] == "ok").to_numpy(dtype=bool))

    def info(self) -> dict[str, Any]:
        """A JSON-ready summary: counts, failures by reason, provenance, feature percentiles and, for an
        adaptive design, its settings and rounds (``design``; None otherwise)."""
        from invphys.core.adaptive_plan import describe_design

        meta = self.metadata
        df = self.frame()
        manifest = self.manifest
        ok = df[df["status"] == "ok"]
        failed = df[df["status"] != "ok"]
        reasons = failed["failure"].fillna("(no reason)").value_counts()
        features: dict[str, dict[str, float | None]] = {}
        for name in meta["feature_names"]:
            col = ok[f"f_{name}"].to_numpy(dtype=np.float64, na_value=np.nan)
            if len(col) and np.isfinite(col).any():
                p5, p50, p95 = np.nanpercentile(col, [5, 50, 95])
                features[name] = {"p5": float(p5), "p50": float(p50), "p95": float(p95)}
            else:
                features[name] = {"p5": None, "p50": None, "p95": None}
        wall = df["wall_time_s"].to_numpy(dtype=np.float64)
        sessions = meta.get("sessions", [])
        return {
            "path": str(self.path),
            "rows": len(df), "ok": len(ok), "failed": len(failed),
            "parts": len(manifest["parts"]) if manifest is not None else len(self.parts()),
            "manifest": manifest is not None,
            "failures_by_reason": {str(k): int(v) for k, v in reasons.items()},
            "identity": meta.get("identity"),
            "simulator": meta.get("simulator"),
            "extractor": meta.get("extractor_block"),
            "param_names": meta["param_names"], "feature_names": meta["feature_names"],
            "devices": sorted(set(df["device"].dropna().astype(str)) - {""}),
            "backends": sorted(set(df["backend"].dropna().astype(str)) - {""}),
            "sim_time_s": {"mean": float(wall.mean()) if len(wall) else None,
                           "total": float(wall.sum())},
            "generation_wall_s": float(sum(s.get("wall_s", 0.0) for s in sessions)),
            "sessions": len(sessions),
            "fingerprint": keys_fingerprint(list(ok["key"])),
            "features": features,
            "created_at": meta.get("created_at"), "updated_at": meta.get("updated_at"),
            "design": describe_design(self.path),
        }


def _check_first_ok(first_ok: int | None) -> None:
    if first_ok is not None and (isinstance(first_ok, bool) or not isinstance(first_ok, int) or first_ok < 1):
        raise ValueError(f"first_ok must be a positive int or None, not {first_ok!r}")


def _too_few_message(path: Path, held: int, wanted: int) -> str:
    return f"dataset {str(path)!r} holds {held} ok rows, fewer than the {wanted} asked for"
