"""The catalog's backup: the save policy (`saver`) over an embedded SQLite file (`sqlite`).

The store knows the catalog's rows and nothing of actors: the registrar hands it the
`Changes` it drained from its catalog, and gets back what a restart restores.
"""

from rr_actors._store.saver import CatalogStore, Saver, open_catalog, open_store
from rr_actors._store.sqlite import (
    APPLICATION_ID,
    SCHEMA_VERSION,
    Backup,
    Restored,
    SqliteStore,
    Unreadable,
    gc_paused,
    quarantine_backup,
    read_backup,
)

__all__ = [
    "APPLICATION_ID",
    "SCHEMA_VERSION",
    "Backup",
    "CatalogStore",
    "Restored",
    "Saver",
    "SqliteStore",
    "Unreadable",
    "gc_paused",
    "open_catalog",
    "open_store",
    "quarantine_backup",
    "read_backup",
]
