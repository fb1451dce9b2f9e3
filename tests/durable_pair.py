"""Durable registrars for the persistence tests: the provider/consumer pair that the crash
tests run in their child processes, `start` for a registrar a test stops at teardown, and
stores and schema-2 files to start from (`opened`, `schema_2_database`)."""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import rr_actors as rr
from rr_actors._catalog import DIGEST_SCHEME, Catalog
from rr_actors._store import schema
from rr_actors._store.sqlite import SqliteStore


def opened(path: Path) -> tuple[SqliteStore, Catalog]:
    """A store with background checkpoints on `path` that holds loaded resource `r1`."""
    store = SqliteStore.open(path, background_checkpoints=True)
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", {"n": 1})
    catalog.finish_load("r1", {"pid": 1})
    store.write(catalog.drain_changes())
    return store, catalog


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


def noop_unload(_request: Any, _response: Any) -> None:
    return None


def start_provider(name: str, path: str) -> rr.ResourceRegistrar:
    """Provider `name` with `save_on_modify` on `path` and a `leaf` server."""
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=name, backup_path=path, save_on_modify=True)
    )
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
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
