"""The catalog's backup: the save policy (`saver`) over an embedded SQLite file.

The store knows the catalog's rows and nothing of actors. Modules, lowest first: `codec`,
`schema`, `restore`, `files`, `plan`, `checkpoints`, `commits`, `outbox`, `sqlite`
(`SqliteStore`), `saver`.
"""

from rr_actors._store.codec import Unreadable
from rr_actors._store.files import Backup, gc_paused, read_backup
from rr_actors._store.restore import Restored
from rr_actors._store.saver import CatalogStore, Saver, open_catalog, open_store
from rr_actors._store.schema import APPLICATION_ID, SCHEMA_VERSION
from rr_actors._store.sqlite import SqliteStore

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
    "read_backup",
]
