"""The durable pair: a provider P and a consumer C with backups (`save_on_modify`).

`pair_backups` names the pair and its backup files; `start_pair` (or `start_provider` and
`start_consumer`) starts it, in a crash test's child process or in the test itself;
`durable_config` is one durable registrar's config (for a manager process). Also `start`
for a registrar a test stops at teardown, and stores and schema-2 files to start from
(`opened`, `schema_2_database`)."""

from __future__ import annotations

import contextlib
import sqlite3
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import rr_actors as rr
from rr_actors._catalog import DIGEST_SCHEME, Catalog
from rr_actors._store import schema
from rr_actors._store.saver import SqliteStore


def new_store(path: Path, **options: Any) -> tuple[SqliteStore, Catalog]:
    """A store opened on `path` (with these options), its backup read, and an empty catalog."""
    store = SqliteStore.open(path, **options)
    store.load()
    return store, Catalog()


def opened(path: Path) -> tuple[SqliteStore, Catalog]:
    """A store with background checkpoints on `path` that holds loaded resource `r1`."""
    store, catalog = new_store(path, background_checkpoints=True)
    catalog.begin_load("r1", "leaf", {"n": 1})
    catalog.finish_load("r1", {"pid": 1})
    store.write(catalog.drain_changes())
    return store, catalog


def written_schema(path: Path) -> tuple[int, list[str]]:
    """The schema version written in the backup at `path`, and its `resources` columns."""
    with contextlib.closing(sqlite3.connect(path)) as db:
        version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]
        return version, [row[1] for row in db.execute("PRAGMA table_info(resources)")]


def schema_2_database(path: Path) -> sqlite3.Connection:
    """An autocommit connection to a new, empty rr_actors backup at schema version 2."""
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(f"PRAGMA application_id = {schema.APPLICATION_ID}")
    for step in schema.MIGRATIONS[:2]:
        step(db)
    db.execute("UPDATE rr_actors_schema SET version = 2, digest_scheme = ?", (DIGEST_SCHEME,))
    return db


def leaf_load(request: Any) -> Any:
    return {"leaf": request}


class PairBackups(NamedTuple):
    """Unique names of P and C and their backup files (`p.db` and `c.db`)."""

    names: tuple[str, str]
    paths: tuple[Path, Path]


def pair_backups(directory: Path) -> PairBackups:
    """Names `P-<8 hex>` and `C-<8 hex>`, backups `directory`/p.db and c.db."""
    tag = uuid.uuid4().hex
    return PairBackups((f"P-{tag[:8]}", f"C-{tag[8:16]}"), (directory / "p.db", directory / "c.db"))


def durable_config(prefix: str, directory: Path) -> rr.RegistrarConfig:
    """Registrar `<prefix>-<8 hex>` with `save_on_modify` on backup `directory`/<name>.db."""
    name = f"{prefix}-{uuid.uuid4().hex[:8]}"
    return rr.RegistrarConfig(name, backup_path=directory / f"{name}.db", save_on_modify=True)


def noop_unload(_request: Any, _response: Any) -> None:
    return None


def start_provider(
    name: str, path: str | Path, load: Callable[[Any], Any] = leaf_load
) -> rr.ResourceRegistrar:
    """Provider `name` with `save_on_modify` on `path` and a `leaf` server (`load`)."""
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=name, backup_path=path, save_on_modify=True)
    )
    provider.register_server("leaf", load=load, unload=noop_unload)
    return provider


def start_pair(
    names: tuple[str, str], paths: tuple[str, str]
) -> tuple[rr.ResourceRegistrar, rr.ResourceRegistrar]:
    """Provider P (servers `leaf` and `nested`, which loads a leaf) and consumer C."""
    p_name, c_name = names
    provider = start_provider(p_name, paths[0])

    def nested(request: Any) -> Any:
        return provider.call(p_name, "leaf", {"sub": request}).response

    provider.register_server("nested", load=nested, unload=noop_unload)
    return provider, start_consumer(c_name, paths[1])


def start_consumer(name: str, path: str) -> rr.ResourceRegistrar:
    """Consumer `name` with `save_on_modify` on `path`."""
    return rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=name, backup_path=path, save_on_modify=True)
    )


def start(
    started: list[rr.ResourceRegistrar], name: str, path: Path | None, **config: Any
) -> rr.ResourceRegistrar:
    """Start registrar `name` on backup `path` (or none); `started` (a fixture) stops it."""
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=name, backup_path=path, **config)
    )
    started.append(registrar)
    return registrar
