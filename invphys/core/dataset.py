"""The dataset store: append-only, crash-safe Parquet parts, a manifest, and a JSON metadata file.

A store is a directory::

    DIR/_metadata.json                 provenance, parameter space, feature names, sessions, totals
    DIR/_manifest.json                 every committed part: name, rows, bytes, sha256
    DIR/part-000000-1a2b3c4d.parquet   one part per flushed batch of rows (never rewritten)
    DIR/part-000001-....parquet
    DIR/_quarantine/                   parts set aside by ``invphys dataset verify --repair``
    DIR/.lock                          held by the one process appending

``pandas.read_parquet(DIR)``, ``pyarrow.dataset.dataset(DIR)``, polars and duckdb read every row (files and
folders starting with ``.`` or ``_`` are skipped). Each part is written under a temporary name, fsynced and
renamed atomically, then recorded in the manifest (also atomically), so a reader never sees half a part
and a killed writer loses only the rows it had not flushed. Each part's Parquet schema metadata carries
the store's provenance (key ``invphys``).

Every row carries a key: a stable hash of its normalised parameters (rounded to :data:`KEY_DECIMALS`
decimals) and the :class:`RunIdentity` (simulator name, preset, backend, version and a hash of its full
config). A re-run skips the keys already present, so it resumes instead of duplicating; a key is never
stored twice. Readers through this API check the store against its manifest on every open and refuse
(naming them) missing, corrupt, foreign or duplicated parts; :meth:`DatasetStore.verify` lists them and

The store is built in parts (:mod:`invphys.core.store`), each small enough to read on its own:
``layout`` (file names, limits, errors, the JSON files), ``keys`` (run identities and row keys), ``rows``
(the Parquet schema and row conversion), ``scan`` (reading and classifying part files), ``append``,
``verify`` (verify and repair) and ``read``. This module is the front door: every public name is here.
"""

from __future__ import annotations

from invphys.core.store.append import Appender
from invphys.core.store.keys import (
    KEY_DECIMALS,
    RunIdentity,
    config_hash,
    extractor_identity,
    keys_fingerprint,
    round_theta,
    row_key,
    row_keys,
)
from invphys.core.store.layout import (
    FORMAT,
    LOCK_FILE,
    MANIFEST_FILE,
    MANIFEST_FORMAT,
    MAX_JSON_BYTES,
    MAX_PART_BYTES,
    METADATA_FILE,
    QUARANTINE_DIR,
    SCHEMA_KEY,
    STRAY_MIN_BYTES,
    DatasetError,
    StoreNotWritableError,
    UnsafeStoreError,
    enclosing_store,
    max_part_bytes,
    provenance,
)
from invphys.core.store.read import Reader
from invphys.core.store.rows import (
    MAX_REASON_CHARS,
    META_COLUMNS,
    DatasetArrays,
    Row,
    check_features,
    failure_reason,
    rows_to_table,
    table_schema,
)
from invphys.core.store.scan import PartProblem
from invphys.core.store.verify import Verifier, VerifyReport

__all__ = [
    "FORMAT",
    "KEY_DECIMALS",
    "LOCK_FILE",
    "MANIFEST_FILE",
    "MANIFEST_FORMAT",
    "MAX_JSON_BYTES",
    "MAX_PART_BYTES",
    "MAX_REASON_CHARS",
    "METADATA_FILE",
    "META_COLUMNS",
    "QUARANTINE_DIR",
    "SCHEMA_KEY",
    "STRAY_MIN_BYTES",
    "DatasetArrays",
    "DatasetError",
    "DatasetStore",
    "PartProblem",
    "Row",
    "RunIdentity",
    "StoreNotWritableError",
    "UnsafeStoreError",
    "VerifyReport",
    "check_features",
    "config_hash",
    "enclosing_store",
    "extractor_identity",
    "failure_reason",
    "keys_fingerprint",
    "max_part_bytes",
    "provenance",
    "round_theta",
    "row_key",
    "row_keys",
    "rows_to_table",
    "table_schema",
]


class DatasetStore(Appender, Verifier, Reader):
    """An append-only store of simulation rows in ``path`` (see the module docstring).

    Writing: :meth:`create_or_check`, :meth:`writer`, :meth:`append` (:mod:`invphys.core.store.append`).
    Integrity: :meth:`verify`, :meth:`repair` (:mod:`invphys.core.store.verify`). Reading: :meth:`frame`,
    :meth:`arrays`, :meth:`keys`, :meth:`ok_count`, :meth:`info`, :meth:`content_fingerprint`
    (:mod:`invphys.core.store.read`). Metadata and manifest: :meth:`metadata`, :meth:`manifest`,
    :meth:`write_metadata`, :meth:`parts` (:mod:`invphys.core.store.base`).
    """
