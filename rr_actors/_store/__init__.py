"""The catalog's backup: the save policy (`saver`) over an embedded SQLite file.

The store knows the catalog's rows and nothing of actors. Modules, lowest first: `schema`
(the SQL: the schema, a row's values, a write's statements), `files` (the path, the lock,
the file and its checks), `restore` (reading it back), `outbox` (the events written with a
change), `saver` (when changes are written, and `SqliteStore`: the writer).
"""

from rr_actors._store.restore import Backup, Restored, gc_paused, read_backup
from rr_actors._store.saver import CatalogStore, Saver, SqliteStore, open_catalog, open_store
from rr_actors._store.schema import APPLICATION_ID, SCHEMA_VERSION, Unreadable

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
