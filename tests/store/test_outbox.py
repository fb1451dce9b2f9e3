"""The backup's outbox: a change's events in its own transaction, read back after a kill
(`_store/outbox.py`; issue 40)."""

from __future__ import annotations

import dataclasses
import json
import sqlite3
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._catalog import Catalog
from rr_actors._store import outbox, schema
from rr_actors._store.outbox import SLOTS, read_told
from rr_actors._store.saver import SqliteStore
from tests.events.test_events import EXAMPLES
from tests.support.durable_pair import new_store, written_schema
from tests.support.persisting import CommitFails, reopen

SCHEMA_6_BACKUP = Path(__file__).parent / "data" / "schema-6-loaded.db"
"""A backup written by rr_actors db5b519 (schema version 6), by this script run with that
tree first on `PYTHONPATH` (then `PRAGMA wal_checkpoint(TRUNCATE)` folded its log in;
its `-commits` file was left out)::

    import os, rr_actors as rr
    reg = rr.ResourceRegistrar.start(rr.RegistrarConfig(
        name="old-erm", backup_path="old.db", save_on_modify=True))
    reg.register_server("leaf", load=lambda r: {"for": r}, unload=lambda r, s: None)
    reg.call("old-erm", "leaf", "lidar", query_id="00000000-0000-4000-8000-000000000006")
    os._exit(0)  # as a SIGKILL
"""


def added(seq: int, pid: int = 4242, query_id: str = "q1") -> events.ConsumerAdded:
    return events.ConsumerAdded(
        "erm", "r1", query_id, "app", at=1.5, pid=pid, seq=seq, host="robot", hlc=seq << 16
    )


def opened(path: Path) -> tuple[SqliteStore, Catalog]:
    store, catalog = new_store(path)
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", 1)
    store.write(catalog.drain_changes())
    return store, catalog


def outbox_rows(path: Path) -> list[tuple[int, int]]:
    db = sqlite3.connect(path)
    try:
        return db.execute("SELECT pid, seq FROM outbox ORDER BY seq").fetchall()
    finally:
        db.close()


def test_a_changes_events_are_committed_with_it_and_read_back_by_its_process(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    store, catalog = opened(path)
    try:
        catalog.add_consumer("r1", "q1", "app")
        store.write(catalog.drain_changes(), (added(7),))
        catalog.add_consumer("r1", "q2", "app")  # another process's, and an unnumbered one
        store.write(catalog.drain_changes(), (added(3, pid=99, query_id="q2"), added(0)))

        found = read_told(path, 4242)  # (while the writer still has it open: as if killed)
    finally:
        store.close(erase=False)

    assert [added(7)] == found
    assert [(99, 3), (4242, 7)] == outbox_rows(path)  # (the one with no number: not written)


@pytest.mark.parametrize("event", EXAMPLES, ids=lambda e: type(e).__name__)
def test_every_event_kind_is_read_back_from_its_row_as_it_was(event: events.Event) -> None:
    assert event == outbox._event(json.loads(outbox._row(event)))


def test_a_write_that_fails_writes_neither_the_change_nor_its_events(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    store, catalog = opened(path)
    store._db = CommitFails(store._db)  # type: ignore[assignment]
    catalog.add_consumer("r1", "q1", "app")
    try:
        with pytest.raises(rr.CatalogWriteError, match="simulated"):
            store.write(catalog.drain_changes(), (added(7),))
    finally:
        store.close(erase=False)

    assert ([], {}) == (outbox_rows(path), dict(reopen(path).resources["r1"].consumers))


def test_the_outbox_keeps_the_last_slots_events_and_no_more(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    store, catalog = opened(path)
    try:
        for seq in range(1, SLOTS + 11):
            catalog.add_consumer("r1", f"q{seq}", "app")
            store.write(catalog.drain_changes(), (added(seq, query_id=f"q{seq}"),))
        found = read_told(path, 4242)
    finally:
        store.close(erase=False)

    assert list(range(11, SLOTS + 11)) == [e.seq for e in found]


def test_the_next_open_of_the_backup_empties_its_outbox(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    store, catalog = opened(path)
    catalog.add_consumer("r1", "q1", "app")
    store.write(catalog.drain_changes(), (added(7),))
    store.close(erase=False)
    assert [(4242, 7)] == outbox_rows(path)

    SqliteStore.open(path).close(erase=False)  # (the registrar's restart)

    assert ([], []) == (outbox_rows(path), read_told(path, 4242))


def test_a_query_forgotten_row_of_schema_4_is_read_without_its_release_stamps(
    tmp_path: Path,
) -> None:
    # a registrar of the version before wrote it (killed), this one reads it at its start
    path = tmp_path / "p.db"
    store, _ = opened(path)
    store.close(erase=False)
    forgot = events.QueryForgotten("cm", "q1", "erm", "unload", 7, 3, pid=4242, seq=5)
    row = json.loads(outbox._row(forgot))
    assert [7, 3, "", ""] == row[6:10]  # (after its type and 4 fields: schema 5's, 7's)
    old = [4, *row[1:6], *row[10:]]
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("INSERT INTO outbox VALUES (5, 4242, 5, ?)", (json.dumps(old),))
    db.close()

    assert [dataclasses.replace(forgot, unload_sent=0, reconciled=0)] == read_told(path, 4242)


def test_a_resource_loaded_row_of_schema_7_is_read_without_its_trace(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    store, _ = opened(path)
    store.close(erase=False)
    trace = f"00-{'1' * 32}-{'2' * 16}-01"
    loaded = events.ResourceLoaded("erm", "leaf", "r1", "q1", 0.5, 7, "x", trace, pid=4242, seq=5)
    row = json.loads(outbox._row(loaded))
    assert trace == row[9]  # (after its type and 7 fields: the one schema 8 added)
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(
        "INSERT INTO outbox VALUES (5, 4242, 5, ?)", (json.dumps([7, *row[1:9], *row[10:]]),)
    )
    db.close()

    assert [dataclasses.replace(loaded, trace="")] == read_told(path, 4242)


def test_a_share_refused_row_of_schema_8_is_read_without_those_waiting(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    store, _ = opened(path)
    store.close(erase=False)
    refused = events.ShareRefused(
        "erm", "leaf", "api", 5, 3, 2, 2, 1, 8, 0.5, (1,), (0.25,), pid=4242, seq=5
    )
    row = json.loads(outbox._row(refused))
    assert [0.5, [1], [0.25]] == row[11:14]  # (after its type and 9 fields: schema 9's)
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(
        "INSERT INTO outbox VALUES (5, 4242, 5, ?)", (json.dumps([8, *row[1:11], *row[14:]]),)
    )
    db.close()

    assert [dataclasses.replace(refused, since=0.0, waiting=(), firsts=())] == read_told(path, 4242)


@pytest.mark.parametrize(
    "row",
    [
        "not json",
        json.dumps({"type": "ConsumerAdded", "schema": 3}),  # fields missing
        '{"type": "ConsumerAdded", "pid": ' + "9" * 5000 + "}",  # a 5,000-digit number
        json.dumps([1, 2, 3]),
        json.dumps(events.to_dict(added(8))),  # an events.jsonl line, not a row
        outbox._row(added(8)),  # an event, in the row of another number
        outbox._row(added(5)).replace(f"[{events.lines.SCHEMA},", "[2,", 1),  # another version
        outbox._row(added(5)).replace('"robot"', "7"),  # a field of the wrong type
        outbox._row(added(5))[:-1] + ',"extra"]',  # one value too many
    ],
)
def test_a_row_that_is_not_its_event_is_skipped_and_the_others_are_read(
    tmp_path: Path, row: str
) -> None:
    path = tmp_path / "p.db"
    store, catalog = opened(path)
    catalog.add_consumer("r1", "q1", "app")
    store.write(catalog.drain_changes(), (added(7),))
    store.close(erase=False)
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("INSERT INTO outbox VALUES (5, 4242, 5, ?)", (row,))
    db.close()

    assert [added(7)] == read_told(path, 4242)


def test_a_file_that_is_no_catalog_or_none_at_all_has_nothing_to_read(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.db"
    garbage.write_bytes(b"not a database" * 100)

    assert ([], []) == (read_told(garbage, 1), read_told(tmp_path / "missing.db", 1))


def test_a_schema_6_backup_is_migrated_with_an_empty_outbox(tmp_path: Path) -> None:
    path = tmp_path / "old.db"
    path.write_bytes(SCHEMA_6_BACKUP.read_bytes())

    catalog = reopen(path)

    assert (schema.SCHEMA_VERSION, []) == (written_schema(path)[0], outbox_rows(path))
    [resource] = catalog.resources.values()
    assert (["00000000-0000-4000-8000-000000000006"], {"for": "lidar"}) == (
        list(resource.consumers),
        resource.response,
    )
