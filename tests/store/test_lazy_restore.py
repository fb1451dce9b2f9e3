"""A lazily restored catalog (schema 3) behaves like one read whole.

A restore leaves most served resources in the backup until a lookup needs them; these
tests pin what that must never change: a damaged row fails only its own use, the order of
listings, and what happens once the backup is closed. (Found by a review of the change.)
"""

from __future__ import annotations

import sqlite3
import uuid
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog, request_digest
from rr_actors._store import codec
from rr_actors._store.files import read_backup
from rr_actors._store.sqlite import SqliteStore
from tests.support.durable_pair import schema_2_database


def write_catalog(path: Path, rows: list[tuple[str, str, Any, str]]) -> None:
    """A backup whose resources (id, server, request, consumer id) are loaded, in order."""
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    for rid, server, request, query_id in rows:
        catalog.begin_load(rid, server, request)
        catalog.finish_load(rid, {"of": rid})
        catalog.add_consumer(rid, query_id, "C")
    store.write(catalog.drain_changes())
    store.close(erase=False)


def damage_request(path: Path, rid: str) -> None:
    db = sqlite3.connect(path)
    db.execute("UPDATE resources SET request = x'00ff00' WHERE id = ?", (rid,))
    db.commit()
    db.close()


def lazily_restored(path: Path) -> tuple[SqliteStore, Catalog]:
    store = SqliteStore.open(path)
    restored = store.restore()
    assert restored is not None
    return store, Catalog.restore(restored.resources, restored.clients, restored.unread)


# -- 1. a damaged row loses the healthy rows read by the same lookup ---------------------------


@pytest.mark.parametrize(
    "lookup",
    [
        lambda catalog: catalog.resources_of("leaf"),
        lambda catalog: catalog.server_queries("leaf", "P"),
        lambda catalog: catalog.consumers_from("C"),
        lambda catalog: catalog.read_all(),
    ],
    ids=["resources_of", "server_queries", "consumers_from", "read_all"],
)
def test_a_damaged_row_does_not_hide_the_healthy_rows_read_by_the_same_lookup(
    tmp_path: Path, lookup: Any
) -> None:
    """A lookup that meets a damaged row fails, and reads none of the rows it met: the
    healthy r0 stays on disk, whole, for the next lookup (not marked read and lost)."""
    path = tmp_path / "p.db"
    write_catalog(path, [("r0", "leaf", {"n": 0}, "q0"), ("r1", "leaf", {"n": 1}, "q1")])
    damage_request(path, "r1")
    store, catalog = lazily_restored(path)
    try:
        with pytest.raises(rr.CatalogCorruptError):
            lookup(catalog)
        found = catalog.find("leaf", {"n": 0})
        known = catalog.has_consumer("q0")
    finally:
        store.close(erase=False)

    # r0 is healthy and on disk: it must still be found, and q0 must still be its consumer
    assert ("r0", True) == (found.id if found is not None else None, known)


def test_a_registrar_loads_a_healthy_restored_resource_again_after_a_damaged_neighbour_failed(
    tmp_path: Path,
) -> None:
    """server_queries fails on the damaged r1; an equal request to the healthy, restored r0
    is still a dedup hit afterwards (no second `load`, the stored response)."""
    path = tmp_path / "p.db"
    write_catalog(path, [("r0", "leaf", {"n": 0}, "q0"), ("r1", "leaf", {"n": 1}, "q1")])
    damage_request(path, "r1")
    loads: list[Any] = []
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"P-{uuid.uuid4().hex[:8]}", backup_path=path, save_interval=None)
    )
    try:
        registrar.register_server(
            "leaf", load=lambda r: loads.append(r) or "fresh", unload=lambda r, s: None
        )
        with pytest.raises(rr.CatalogCorruptError):
            registrar.server_queries("leaf")
        served = registrar.call(registrar.name, "leaf", {"n": 0})
        registrar.unload(served.id)
    finally:
        registrar.stop()

    assert ([], {"of": "r0"}) == (loads, served.response)


# -- 2. read_all is not in stored order once lookups read every row ----------------------------


def test_read_all_lists_restored_resources_oldest_first_even_when_lookups_read_them_all(
    tmp_path: Path,
) -> None:
    """Listings are oldest first, also when lookups read the restored rows in another order
    (and read the last of them, so nothing is left unread)."""
    path = tmp_path / "p.db"
    write_catalog(path, [("r0", "a", "zero", "q0"), ("r1", "b", "one", "q1")])
    stored = [r.id for r in read_backup(path).resources]

    store, before = lazily_restored(path)
    try:
        untouched = list(before.read_all())  # read_all() with rows still unread: sorted
    finally:
        store.close(erase=False)
    store, catalog = lazily_restored(path)
    try:
        catalog.resource_of("q1")  # reads r1 first
        catalog.resource_of("q0")  # then r0: nothing is left unread
        listed = list(catalog.read_all())
    finally:
        store.close(erase=False)

    assert (["r0", "r1"], ["r0", "r1"]) == (stored, untouched)
    assert stored == listed


# -- 3. a closed backup, an open transaction, a tampered key ----------------------------------


def test_a_lookup_that_needs_the_backup_after_it_was_closed_says_the_registrar_stopped(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_catalog(path, [("r0", "leaf", {"n": 0}, "q0")])
    store, catalog = lazily_restored(path)
    store.close(erase=False)  # what a stop or a crash does before the mailbox is empty

    with pytest.raises(rr.RegistrarStoppedError, match="was closed"):
        catalog.has_consumer("q0")
    with pytest.raises(rr.RegistrarStoppedError, match="was closed"):
        catalog.find("leaf", {"n": 0})


def test_a_write_inside_a_transaction_left_open_fails_loudly_and_is_kept_for_the_next(
    tmp_path: Path,
) -> None:
    """A failed ROLLBACK may leave a transaction open: a one-statement write must not then
    run inside it (it would never be committed) but fail, and stay pending."""
    path = tmp_path / "p.db"
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", 1)
    store.write(catalog.drain_changes())
    catalog.add_consumer("r1", "q1", "C")
    changes = catalog.drain_changes()
    store._db.execute("BEGIN")
    try:
        with pytest.raises(rr.CatalogWriteError, match="within a transaction"):
            store.write(changes)
        store._db.execute("ROLLBACK")
        store.write(changes)
    finally:
        store.close(erase=False)

    assert [("r1", ["q1"])] == [(r.id, list(r.consumers)) for r in read_backup(path).resources]


def test_a_consumer_row_whose_resource_key_is_not_a_number_is_a_corrupt_backup(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_catalog(path, [("r0", "leaf", {"n": 0}, "q0")])
    db = sqlite3.connect(path)
    db.execute("UPDATE consumers SET resource = 'x' WHERE query_id = 'q0'")
    db.commit()
    db.close()
    store, catalog = lazily_restored(path)
    try:
        with pytest.raises(rr.CatalogCorruptError) as raised:
            catalog.resource_of("q0")
    finally:
        store.close(erase=False)

    assert str(path) == raised.value.path


# -- 4. a schema-2 file --------------------------------------------------------------------------


def write_v2_backup(path: Path) -> None:
    """A backup laid out as rr_actors wrote it with schema version 2 (rowid consumers).

    r0 (loaded, consumers q0 then q1 in arrival order, owner of dependency d0), r1 still
    loading (in doubt), r2 loaded; the consumer seqs are not in resource order.
    """
    db = schema_2_database(path)
    dumps = codec.dumps
    for seq, rid, state, request in ((1, "r0", 1, {"n": 0}), (2, "r1", 0, "x"), (5, "r2", 1, 2)):
        db.execute(
            "INSERT INTO resources VALUES (?, ?, 'leaf', ?, ?, ?, ?)",
            (seq, rid, state, request_digest(request), dumps(request), dumps({"of": rid})),
        )
    for seq, query_id, resource in ((3, "q0", 1), (4, "q2", 5), (6, "q1", 1)):
        db.execute("INSERT INTO consumers VALUES (?, ?, ?, 'C')", (seq, query_id, resource))
    db.execute(
        "INSERT INTO clients VALUES (7, 'd0', 'leaf', 'Q', 'me', ?, NULL, 'r0', 1)",
        (dumps(5),),
    )
    db.execute("PRAGMA journal_mode = WAL")
    db.close()


def test_a_version_2_backup_is_migrated_and_restored_lazily(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    write_v2_backup(path)

    store = SqliteStore.open(path)
    try:
        restored = store.restore()
        assert restored is not None
        at_once = sorted(r.id for r in restored.resources)  # in doubt, or owns a dependency
        catalog = Catalog.restore(restored.resources, restored.clients, restored.unread)
        found = catalog.find("leaf", 2)
        listed = [(r.id, list(r.consumers)) for r in catalog.read_all().values()]
        catalog.release("q1")
        catalog.add_consumer("r2", "q3", "C")
        store.write(catalog.drain_changes())
    finally:
        store.close(erase=False)

    assert (["r0", "r1"], "r2") == (at_once, found.id if found else None)
    assert [("r0", ["q0", "q1"]), ("r1", []), ("r2", ["q2"])] == listed
    assert [("r0", ["q0"]), ("r1", []), ("r2", ["q2", "q3"])] == [
        (r.id, list(r.consumers)) for r in read_backup(path).resources
    ]


# -- 4b. a schema-4 file: its consumer ids get their index ----------------------------------------


def as_version_4(path: Path) -> None:
    """Make a current backup what schema version 4 wrote: no index on the consumer ids
    (nor the `failed` column of version 6, nor the outbox of version 7)."""
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("DROP TABLE outbox")
    db.execute("DROP INDEX consumers_by_query")
    db.execute("ALTER TABLE resources DROP COLUMN failed")
    db.execute("UPDATE rr_actors_schema SET version = 4")
    db.close()


def test_a_version_4_backup_gets_its_consumer_index_and_finds_every_consumer(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_catalog(path, [(f"r{n}", "leaf", {"n": n}, f"q{n}") for n in range(3)])
    as_version_4(path)
    store, catalog = lazily_restored(path)
    try:
        found = [catalog.resource_of(f"q{n}").id for n in (2, 0)]
        indexes = {
            name
            for (name,) in store.connection.execute(
                "SELECT name FROM sqlite_master WHERE type = 'index'"
            )
        }
    finally:
        store.close(erase=False)

    assert (["r2", "r0"], True) == (found, "consumers_by_query" in indexes)


def test_a_version_4_backup_with_a_consumer_id_stored_twice_is_refused_and_left_as_it_was(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_catalog(path, [("r0", "leaf", {"n": 0}, "q0"), ("r1", "leaf", {"n": 1}, "q1")])
    as_version_4(path)
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("UPDATE consumers SET query_id = 'q0' WHERE query_id = 'q1'")
    db.close()

    with pytest.raises(rr.CatalogCorruptError) as raised:
        SqliteStore.open(path)

    db = sqlite3.connect(path)
    version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]
    db.close()
    assert (str(path), True, 4) == (raised.value.path, "UNIQUE" in raised.value.cause, version)
