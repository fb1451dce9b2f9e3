"""The catalog's backup: the save policy (`saver`) over an embedded SQLite file.

The store knows the catalog's rows and nothing of actors. Modules, lowest first: `schema`
(the SQL: the schema, a row's values, a write's statements), `files` (the path, the lock,
the file and its checks), `restore` (reading it back), `outbox` (the events written with a
change), `sqlite` (`SqliteStore`: the writer), `saver` (when changes are written).
"""

from rr_actors._store.restore import Backup, Restored, gc_paused, read_backup
from rr_actors._store.saver import CatalogStore, Saver, open_catalog, open_store
from rr_actors._store.schema import APPLICATION_ID, SCHEMA_VERSION, Unreadable
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
