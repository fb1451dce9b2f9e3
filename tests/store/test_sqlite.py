"""The SQLite store on its own: what is written reads back, every response the catalog sets is
written, and failures while writing (`_store/sqlite.py`).
"""

from __future__ import annotations

import random
import sqlite3
import tempfile
import threading
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import rr_actors as rr
from rr_actors._catalog import (
    Catalog,
    Changes,
    ClientRecord,
    ResourceState,
)
from rr_actors._store import codec, schema
from rr_actors._store import saver as _persistence
from rr_actors._store.files import read_backup
from rr_actors._store.sqlite import SqliteStore
from tests.support.durable_pair import start_provider
from tests.support.persisting import (
    CommitFails,
    FlakyStore,
    InsertFailsOnce,
    make_query,
    random_program,
    reopen,
    rows_of,
    unique,
    written_once,
)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32), batch=st.integers(1, 6))
def test_a_reopened_backup_holds_exactly_the_catalog_written_in_any_batching(
    seed: int, batch: int
) -> None:
    rng = random.Random(seed)  # noqa: S311 - a reproducible test program, not crypto
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "p.db"
        store = SqliteStore.open(path)
        assert store.load() is None
        catalog = Catalog()
        try:
            for step, _ in enumerate(random_program(rng, catalog, 60)):
                if step % batch == 0:
                    store.write(catalog.drain_changes())
            store.write(catalog.drain_changes())
        finally:
            store.close(erase=False)

        assert rows_of(catalog) == rows_of(reopen(path))


def test_a_write_that_fails_leaves_the_file_and_the_next_write_intact(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", 1)
    store.write(catalog.drain_changes())
    catalog.finish_load("r1", threading.Lock())  # cannot be pickled
    catalog.add_consumer("r1", "q1", "C")
    with pytest.raises(TypeError):
        store.write(catalog.drain_changes())
    before = rows_of(reopen(tmp_path / "p.db"))
    catalog.set_response("r1", "fine")
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert ([("r1", ResourceState.LOADING, [])], [("r1", ResourceState.LOADED, [("q1", "C")])]) == (
        [(r[0], r[4], r[5]) for r in before[0]],
        [(r[0], r[4], r[5]) for r in rows_of(reopen(tmp_path / "p.db"))[0]],
    )


def test_an_older_schema_is_migrated_by_an_explicit_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    SqliteStore.open(tmp_path / "p.db").close(erase=False)

    def add_note(db: sqlite3.Connection) -> None:
        db.execute("ALTER TABLE resources ADD COLUMN note TEXT")

    next_version = schema.SCHEMA_VERSION + 1
    monkeypatch.setattr(schema, "MIGRATIONS", (*schema.MIGRATIONS, add_note))
    monkeypatch.setattr(schema, "SCHEMA_VERSION", next_version)
    SqliteStore.open(tmp_path / "p.db").close(erase=False)

    db = sqlite3.connect(tmp_path / "p.db")
    try:
        version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]
        columns = [row[1] for row in db.execute("PRAGMA table_info(resources)")]
    finally:
        db.close()
    assert (next_version, "note") == (version, columns[-1])


def test_setting_a_restored_never_decoded_response_to_none_is_written(tmp_path: Path) -> None:
    written_once(tmp_path / "p.db")
    store = SqliteStore.open(tmp_path / "p.db")
    rows = store.load()
    assert rows is not None
    catalog = Catalog.restore(*rows)
    catalog.set_response("r1", None)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert reopen(tmp_path / "p.db").resources["r1"].response is None


def test_a_response_mutated_in_place_and_set_again_is_written(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    response = {"status": "starting"}
    catalog.begin_load("r1", "leaf", "req")
    catalog.finish_load("r1", response)
    store.write(catalog.drain_changes())
    response["status"] = "running"
    catalog.set_response("r1", response)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert {"status": "running"} == reopen(tmp_path / "p.db").resources["r1"].response


def test_a_client_response_mutated_in_place_and_loaded_again_is_written(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    response = {"status": "starting"}
    catalog.add_client(ClientRecord(make_query("d1", 1)))
    catalog.client_loaded("d1", response)
    store.write(catalog.drain_changes())
    response["status"] = "running"
    catalog.client_loaded("d1", response)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert {"status": "running"} == reopen(tmp_path / "p.db").clients["d1"].query.response


def test_decoding_a_restored_response_writes_no_value(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    written_once(tmp_path / "p.db")
    store = SqliteStore.open(tmp_path / "p.db")
    rows = store.load()
    assert rows is not None
    catalog = Catalog.restore(*rows)
    _ = catalog.resources["r1"].response, catalog.clients["d1"].query.response
    catalog.add_consumer("r1", "q2", "C")  # dirties the row
    dumped: list[Any] = []
    monkeypatch.setattr(codec, "dumps", dumped.append)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert ([], ["q1", "q2"]) == (dumped, list(reopen(tmp_path / "p.db").resources["r1"].consumers))


def test_a_registrar_restarted_writes_update_response_to_none_on_a_restored_query(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    name = unique("P")

    provider = start_provider(name, path, lambda _request: {"pid": 42})
    consumer = rr.ResourceRegistrar.start(unique("C"))
    try:
        query = consumer.call(name, "leaf", {"cmd": "x"}, timeout=5)
        provider.stop()
        provider = start_provider(name, path, lambda _request: {"pid": 42})
        provider.update_response(query.id, None)
        provider.stop()
    finally:
        consumer.stop()
        provider.stop()

    assert [None] == [r.response for r in read_backup(path).resources]


def test_a_failed_commit_raises_its_own_error_not_one_from_the_rollback(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", 1)
    catalog.add_consumer("r1", "q1", "C")  # two statements: one transaction with a COMMIT
    store._db = CommitFails(store._db)  # type: ignore[assignment]
    try:
        with pytest.raises(rr.CatalogWriteError) as raised:
            store.write(catalog.drain_changes())
    finally:
        store.close(erase=False)

    assert "disk I/O error (simulated)" == str(raised.value.__cause__)


def test_a_one_statement_write_that_failed_is_written_again_with_the_next_change(
    tmp_path: Path,
) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", 1)
    store.write(catalog.drain_changes())
    store._db = InsertFailsOnce(store._db)  # type: ignore[assignment]
    catalog.add_consumer("r1", "q1", "C")  # one INSERT: its own transaction
    failed = catalog.drain_changes()
    try:
        with pytest.raises(rr.CatalogWriteError, match="simulated"):
            store.write(failed)
        catalog.add_consumer("r1", "q2", "C")
        store.write(catalog.drain_changes())  # the row holds q1 and q2: both are written
    finally:
        store.close(erase=False)

    assert [("r1", [("q1", "C"), ("q2", "C")])] == [
        (r.id, list(r.consumers.items())) for r in read_backup(tmp_path / "p.db").resources
    ]


def test_a_clean_stop_closes_the_store_even_when_the_last_flush_fails() -> None:
    store = FlakyStore(fail=1)
    saver = _persistence.Saver(store, rr.RegistrarConfig(name="x", backup_path="flaky"))
    saver.changed(Changes({"r1": None}, {}))

    with pytest.raises(rr.CatalogWriteError, match="simulated"):
        saver.close(erase=False)

    assert (True, None) == (store.closed, saver.store)


def test_a_change_whose_save_on_modify_write_failed_is_written_with_the_next_change() -> None:
    store = FlakyStore(fail=1)
    config = rr.RegistrarConfig(name="x", backup_path="flaky", save_on_modify=True)
    saver = _persistence.Saver(store, config)
    with pytest.raises(rr.CatalogWriteError, match="simulated"):
        saver.changed(Changes({"r1": None}, {}))
    saver.changed(Changes({"r2": None}, {"d1": None}))

    assert [(["r1", "r2"], ["d1"])] == store.written


def test_changes_whose_interval_flush_failed_are_written_with_the_next_flush() -> None:
    store = FlakyStore(fail=1)
    saver = _persistence.Saver(store, rr.RegistrarConfig(name="x", backup_path="flaky"))
    saver.changed(Changes({"r1": None}, {}))
    with pytest.raises(rr.CatalogWriteError, match="simulated"):
        saver.flush()
    saver.changed(Changes({"r2": None}, {"d1": None}))
    saver.flush()

    assert [(["r1", "r2"], ["d1"])] == store.written
