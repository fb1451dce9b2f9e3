"""The save policies: save_on_modify, the save interval, clean stops, erase_on_destruct
(rules 13-14); and the SQLite writer on its own: what is written reads back, every response
the catalog sets is written, failures while writing, its checkpoints, and crashes while
writing (`_store/saver.py`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import multiprocessing
import multiprocessing.context
import multiprocessing.forkserver
import os
import random
import signal
import sqlite3
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterator
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
from rr_actors._core import runtime
from rr_actors._store import saver as _persistence
from rr_actors._store import schema
from rr_actors._store.files import lost_commits, read_only
from rr_actors._store.restore import read_backup
from rr_actors._store.saver import SqliteStore, open_store
from rr_actors.testing import catalog_snapshot, crash
from tests.support.durable_pair import (
    leaf_load,
    new_store,
    noop_unload,
    opened,
    pair_backups,
    start,
    start_pair,
    start_provider,
    written_schema,
)
from tests.support.persisting import (
    CommitFails,
    FlakyStore,
    InsertFailsOnce,
    ManualTimers,
    RunAndKill,
    child_hold,
    consumer_ids,
    make_query,
    random_program,
    reopen,
    rows_of,
    unique,
    written_once,
)
from tests.support.powercut import flush_points, logged_disk, mounted_image
from tests.support.syscalls import started, traced


def test_restored_is_false_on_a_first_start(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    registrar = start(started, unique("P"), tmp_path / "p.db")

    assert registrar.restored is False


def test_restored_is_true_on_an_existing_backup_even_an_empty_one(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    name = unique("P")
    start(started, name, tmp_path / "p.db").stop()

    assert start(started, name, tmp_path / "p.db").restored is True


def test_save_on_modify_commits_a_load_before_the_caller_gets_the_answer(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    provider = start(started, unique("P"), tmp_path / "p.db", save_on_modify=True)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)

    query = provider.call(provider.name, "leaf", 1)

    assert {query.id} == consumer_ids(tmp_path / "p.db")


def test_save_on_modify_commits_the_consumers_record_before_the_caller_gets_the_answer(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    provider = start(started, unique("P"), tmp_path / "p.db")
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    consumer = start(started, unique("C"), tmp_path / "c.db", save_on_modify=True)
    answered = threading.Event()
    result: list[rr.Query] = []

    def call() -> None:
        result.append(consumer.call(provider.name, "leaf", 1, timeout=20))
        answered.set()

    # Another connection holds the consumer's backup's write lock: the provider can
    # answer, but the consumer cannot commit its record, so the caller must not be told.
    blocker = sqlite3.connect(tmp_path / "c.db", isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")
    caller = threading.Thread(target=call)
    try:
        caller.start()
        assert not answered.wait(0.5), "answered before its client record was durable"
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
    caller.join(20)

    assert answered.is_set()
    assert [(result[0].id, True)] == [
        (c.query.id, c.loaded) for c in read_backup(tmp_path / "c.db").clients
    ]


def test_save_on_modify_commits_an_unload_before_the_caller_gets_the_answer(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    provider = start(started, unique("P"), tmp_path / "p.db", save_on_modify=True)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    query = provider.call(provider.name, "leaf", 1)

    provider.unload(query.id)

    assert ([], []) == (
        read_backup(tmp_path / "p.db").resources,
        read_backup(tmp_path / "p.db").clients,
    )


def test_without_save_on_modify_a_change_waits_for_the_save_interval(
    tmp_path: Path, started: list[rr.ResourceRegistrar], timers: ManualTimers
) -> None:
    provider = start(started, unique("P"), tmp_path / "p.db", save_interval=30.0)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)

    provider.call(provider.name, "leaf", 1)

    assert set() == consumer_ids(tmp_path / "p.db")


def test_the_save_interval_timer_flushes_pending_changes_and_is_armed_again(
    tmp_path: Path, started: list[rr.ResourceRegistrar], timers: ManualTimers
) -> None:
    provider = start(started, unique("P"), tmp_path / "p.db", save_interval=30.0)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    query = provider.call(provider.name, "leaf", 1)
    assert timers.armed.wait(5)

    delay = timers.fire()
    catalog_snapshot(provider)  # the flush message was handled before this answer

    assert (30.0, {query.id}, True) == (
        delay,
        consumer_ids(tmp_path / "p.db"),
        timers.armed.wait(5),
    )


def test_a_crash_loses_only_the_changes_made_since_the_last_interval_flush(
    tmp_path: Path, timers: ManualTimers
) -> None:
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=unique("P"), backup_path=tmp_path / "p.db", save_interval=30.0)
    )
    try:
        provider.register_server("leaf", load=leaf_load, unload=noop_unload)
        kept = provider.call(provider.name, "leaf", 1)
        assert timers.armed.wait(5)
        timers.fire()
        provider.call(provider.name, "leaf", 2)
    finally:
        crash(provider)

    assert {kept.id} == consumer_ids(tmp_path / "p.db")


def test_save_catalog_writes_pending_changes_at_once(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    provider = start(started, unique("P"), tmp_path / "p.db", save_interval=None)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    query = provider.call(provider.name, "leaf", 1)

    provider.save_catalog()

    assert {query.id} == consumer_ids(tmp_path / "p.db")


def test_a_clean_stop_flushes_pending_changes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """And logs no ERROR: its backup is not damaged (the mutant `saver.py:167:AddNot` told
    the changes lost to a damaged file, `damaged (None)`, and flushed them)."""
    caplog.set_level(logging.ERROR, logger="rr_actors")
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=unique("P"), backup_path=tmp_path / "p.db", save_interval=None)
    )
    consumer = rr.ResourceRegistrar.start(unique("C"))
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    query = consumer.call(provider.name, "leaf", 1)

    provider.stop()
    consumer.stop()

    assert {query.id} == consumer_ids(tmp_path / "p.db")
    assert [] == [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]


def test_erase_on_destruct_removes_the_backup_after_a_clean_stop(tmp_path: Path) -> None:
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=unique("P"), backup_path=tmp_path / "p.db", erase_on_destruct=True)
    )

    registrar.stop()

    assert [] == list(tmp_path.iterdir())


def test_erase_on_destruct_keeps_the_backup_after_a_kill(
    tmp_path: Path, run_and_kill: RunAndKill
) -> None:
    names, paths = pair_backups(tmp_path)

    run_and_kill(child_hold, names, tuple(map(str, paths)))

    assert (True, True) == (paths[0].is_file(), paths[1].is_file())


@pytest.mark.parametrize(("durability", "synchronous"), [("process", 1), ("power", 2)])
def test_durability_chooses_the_sqlite_synchronous_level(
    tmp_path: Path, durability: Any, synchronous: int
) -> None:
    store = SqliteStore.open(tmp_path / "p.db", durability=durability)
    try:
        level = store._db.execute("PRAGMA synchronous").fetchone()[0]
        mode = store._db.execute("PRAGMA journal_mode").fetchone()[0]
    finally:
        store.close(erase=False)

    assert (synchronous, "wal") == (level, mode)


def test_a_new_backup_records_its_schema_version_and_application_id(tmp_path: Path) -> None:
    SqliteStore.open(tmp_path / "p.db").close(erase=False)

    db = sqlite3.connect(tmp_path / "p.db")
    try:
        found = (
            db.execute("SELECT version FROM rr_actors_schema").fetchall(),
            db.execute("PRAGMA application_id").fetchone()[0],
        )
    finally:
        db.close()

    assert ([(schema.SCHEMA_VERSION,)], schema.APPLICATION_ID) == found


WAIT = 10.0  # seconds: the bound of every wait that must succeed
NOT_YET = 0.5  # seconds a caller must stay unanswered while the backup is locked


@contextlib.contextmanager
def write_locked(path: Path) -> Iterator[None]:
    """Another connection holds the backup's write lock: no commit can land meanwhile."""
    blocker = sqlite3.connect(path, isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")
    try:
        yield
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()


def finish_while_locked(
    path: Path,
    entered: threading.Event,
    proceed: threading.Event,
    answered: threading.Event,
    thread: threading.Thread,
    not_yet: str,
) -> None:
    """Once the callback runs (`entered`), let it finish (`proceed`) while the backup is
    write-locked: the caller must stay unanswered (`not_yet` otherwise), then be answered
    once the lock is gone."""
    try:
        assert entered.wait(WAIT)
        with write_locked(path):
            proceed.set()
            assert not answered.wait(NOT_YET), not_yet
    finally:
        proceed.set()
    assert answered.wait(WAIT)
    thread.join(WAIT)


def in_thread(call: Callable[[], Any]) -> tuple[threading.Thread, threading.Event, list[Any]]:
    """Run `call` on a thread; the event is set once it returned (or raised)."""
    done = threading.Event()
    result: list[Any] = []

    def run() -> None:
        try:
            result.append(call())
        except BaseException as exc:
            result.append(exc)
        finally:
            done.set()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, done, result


# -- save_on_modify: committed before the caller's answer ---------------------------------------


def test_save_on_modify_commits_a_second_consumer_of_a_loaded_resource_before_answering(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "p.db"
    provider = start(started, unique("P"), path, save_on_modify=True)
    provider.register_server("leaf", load=lambda r: {"pid": 1}, unload=noop_unload)
    consumer = start(started, unique("C"), None)  # no backup: only the provider commits
    first = consumer.call(provider.name, "leaf", {"n": 1})

    with write_locked(path):  # the dedup hit cannot commit its consumer id
        thread, answered, result = in_thread(
            lambda: consumer.call(provider.name, "leaf", {"n": 1}, timeout=WAIT)
        )
        assert not answered.wait(NOT_YET), "answered before its consumer id was durable"
    assert answered.wait(WAIT)
    thread.join(WAIT)

    second = result[0]
    assert isinstance(second, rr.Query)
    assert {first.id, second.id} == consumer_ids(path)


def test_save_on_modify_commits_a_finished_load_before_answering(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "p.db"
    entered, proceed = threading.Event(), threading.Event()

    def load(_request: Any) -> Any:
        entered.set()
        proceed.wait(WAIT)
        return {"pid": 7}

    provider = start(started, unique("P"), path, save_on_modify=True)
    provider.register_server("leaf", load=load, unload=noop_unload)
    consumer = start(started, unique("C"), None)  # no backup: only the provider commits
    thread, answered, result = in_thread(
        lambda: consumer.call(provider.name, "leaf", {"n": 1}, timeout=WAIT)
    )
    # the LOADING row is committed; the load runs
    finish_while_locked(
        path, entered, proceed, answered, thread, "answered before the LOADED row was durable"
    )

    query = result[0]
    assert isinstance(query, rr.Query)
    [resource] = read_backup(path).resources
    assert ({query.id}, {"pid": 7}) == (set(resource.consumers), resource.response)


def test_save_on_modify_commits_an_unload_before_answering(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "p.db"
    entered, proceed = threading.Event(), threading.Event()

    def unload(_request: Any, _response: Any) -> None:
        entered.set()
        proceed.wait(WAIT)

    provider = start(started, unique("P"), path, save_on_modify=True)
    provider.register_server("leaf", load=lambda r: {"pid": 1}, unload=unload)
    consumer = start(started, unique("C"), None)  # no backup: only the provider commits
    query = consumer.call(provider.name, "leaf", {"n": 1})
    thread, answered, result = in_thread(lambda: consumer.unload(query.id, timeout=WAIT))
    # the UNLOADING row is committed; the callback runs
    finish_while_locked(
        path, entered, proceed, answered, thread, "answered before the removal was durable"
    )

    assert ([None], []) == (result, read_backup(path).resources)


def test_save_on_modify_commits_the_loaded_client_record_before_answering(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    entered, proceed = threading.Event(), threading.Event()

    def load(_request: Any) -> Any:
        entered.set()
        proceed.wait(WAIT)
        return {"pid": 7}

    provider = start(started, unique("P"), None)
    provider.register_server("leaf", load=load, unload=noop_unload)
    path = tmp_path / "c.db"
    consumer = start(started, unique("C"), path, save_on_modify=True)
    thread, answered, result = in_thread(
        lambda: consumer.call(provider.name, "leaf", 1, timeout=WAIT)
    )
    # the pending record is committed; the provider loads
    finish_while_locked(
        path, entered, proceed, answered, thread, "answered before the client record was durable"
    )

    query = result[0]
    assert isinstance(query, rr.Query)
    assert [(query.id, True, {"pid": 7})] == [
        (c.query.id, c.loaded, c.query.response) for c in read_backup(path).clients
    ]


# -- save_interval: the default timer really fires ---------------------------------------------


def test_the_default_save_interval_timer_flushes_on_its_own(
    tmp_path: Path, started: list[rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
) -> None:
    fired = threading.Event()
    real_timer = runtime.thread_timer

    def observed(delay: float, tick: Callable[[], None]) -> runtime.Cancellable:
        def tick_and_tell() -> None:
            tick()  # tells the registrar to flush ...
            fired.set()  # ... before the test hears of it

        return real_timer(delay, tick_and_tell)

    monkeypatch.setattr(_persistence, "timer_factory", observed)
    path = tmp_path / "p.db"
    provider = start(started, unique("P"), path, save_interval=0.05)
    provider.register_server("leaf", load=lambda r: r, unload=noop_unload)
    query = provider.call(provider.name, "leaf", 1)
    fired.clear()

    assert fired.wait(WAIT), "the save-interval timer never fired"
    catalog_snapshot(provider)  # handled after the flush message the tick sent
    assert query.id in consumer_ids(path)


# -- durability through the registrar's configuration -----------------------------------------


@pytest.mark.parametrize(("durability", "synchronous"), [("process", 1), ("power", 2)])
def test_a_registrars_durability_reaches_the_sqlite_connection(
    tmp_path: Path, durability: Any, synchronous: int
) -> None:
    config = rr.RegistrarConfig(name="R", backup_path=tmp_path / "p.db", durability=durability)
    store = open_store(config)
    assert isinstance(store, SqliteStore)
    try:
        level = store._db.execute("PRAGMA synchronous").fetchone()[0]
    finally:
        store.close(erase=False)

    assert synchronous == level


# -- erase_on_destruct only after a clean stop ---------------------------------------------------


def test_erase_on_destruct_keeps_the_backup_of_a_registrar_that_crashed(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(
            name=unique("P"), backup_path=path, save_on_modify=True, erase_on_destruct=True
        )
    )
    try:
        registrar.register_server("leaf", load=lambda r: r, unload=noop_unload)
        query = registrar.call(registrar.name, "leaf", 1)
    finally:
        crash(registrar)

    assert (True, {query.id}) == (path.is_file(), consumer_ids(path))


def test_a_staged_turn_that_adds_or_releases_one_consumer_writes_one_statement_whatever_the_holders(
    tmp_path: Path,
) -> None:
    # a durable registrar's turn stages its changes (`Saver.stage`) and writes them at
    # its end: the consumer ids it added or released go with them, so the write looks at
    # those only, never at every holder of a widely shared resource

    store = SqliteStore.open(tmp_path / "p.db")
    saver = _persistence.Saver(store, rr.RegistrarConfig(name=unique("S"), save_on_modify=True))
    statements = one_added_one_released(store, 100, saver.stage, saver.write)
    saver.close(erase=False)

    assert [
        "BEGIN IMMEDIATE",
        "INSERT INTO consumers (resource, seq, query_id, origin_rr) VALUES (1, 102, 'new', 'C')",
        "DELETE FROM consumers WHERE resource = 1 AND seq = 2",
        "COMMIT",
    ] == statements


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


class Unwalked(dict[str, str]):
    """A resource's consumers that fail a test when something walks all of them."""

    def walked(self, *_: Any) -> Any:
        raise AssertionError("a write walked every holder of the resource")

    __iter__ = keys = values = items = walked


def one_added_one_released(
    store: SqliteStore,
    holders: int,
    stage: Callable[[Changes], None],
    write: Callable[[], None] = lambda: None,
) -> list[str]:
    """The SQL statements `store` ran while consumer `new` of r1 was added, then `h0`
    released: r1 loaded and held by `holders` consumers `h<n>` (staged and written first),
    its consumers `Unwalked`; each change staged, then one `write` (the turn's end)."""
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", "loaded")
    for n in range(holders):
        catalog.add_consumer("r1", f"h{n}", "C")
    stage(catalog.drain_changes())
    write()
    resource = catalog.resources["r1"]
    resource.consumers = Unwalked(resource.consumers)
    statements: list[str] = []
    store._db.set_trace_callback(statements.append)
    catalog.add_consumer("r1", "new", "C")
    stage(catalog.drain_changes())
    catalog.release("h0")
    stage(catalog.drain_changes())
    write()
    return statements


@pytest.mark.parametrize("holders", [1, 1000])
def test_a_write_that_adds_or_releases_one_consumer_is_one_statement_whatever_the_holders(
    tmp_path: Path, holders: int
) -> None:
    path = tmp_path / "p.db"
    store, _ = new_store(path)
    statements = one_added_one_released(store, holders, store.write)
    store.close(erase=False)

    inserted = f"VALUES (1, {holders + 2}, 'new', 'C')"
    assert [
        f"INSERT INTO consumers (resource, seq, query_id, origin_rr) {inserted}",
        "DELETE FROM consumers WHERE resource = 1 AND seq = 2",
    ] == statements
    held = reopen(path).resources["r1"].consumers
    assert ([f"h{n}" for n in range(1, holders)] + ["new"], {"C"}) == (
        list(held),
        set(held.values()),
    )


def test_a_write_after_changes_were_dropped_writes_every_consumer_difference(
    tmp_path: Path,
) -> None:
    """A registrar drops the changes of an in-doubt resource it holds, then marks it
    changed once settled (`mark_changed`): that write compares every consumer, so those
    added and released meanwhile reach the file too."""
    path = tmp_path / "p.db"
    store, catalog = new_store(path)
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", "loaded")
    for query_id in ("a", "b"):
        catalog.add_consumer("r1", query_id, "C")
    store.write(catalog.drain_changes())
    catalog.add_consumer("r1", "c", "C")
    catalog.release("a")
    catalog.drain_changes()  # (dropped: held)
    catalog.mark_changed("r1")

    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert ["b", "c"] == list(reopen(path).resources["r1"].consumers)


def test_a_write_that_fails_leaves_the_file_and_the_next_write_intact(tmp_path: Path) -> None:
    store, catalog = new_store(tmp_path / "p.db")
    catalog.begin_load("r1", "leaf", 1)
    store.write(catalog.drain_changes())
    catalog.finish_load("r1", threading.Lock())  # cannot be pickled
    catalog.add_consumer("r1", "q1", "C")
    with pytest.raises(TypeError):
        store.write(catalog.drain_changes())
    on_disk = read_backup(tmp_path / "p.db")  # (read-only: the store still has it open)
    before = rows_of(Catalog.restore(on_disk.resources, on_disk.clients))
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

    version, columns = written_schema(tmp_path / "p.db")
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
    store, catalog = new_store(tmp_path / "p.db")
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
    store, catalog = new_store(tmp_path / "p.db")
    response = {"status": "starting"}
    catalog.add_client(ClientRecord(make_query("d1", 1)))
    catalog.client_loaded("d1", response)
    store.write(catalog.drain_changes())
    response["status"] = "running"
    catalog.client_loaded("d1", response)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert {"status": "running"} == reopen(tmp_path / "p.db").client("d1").query.response


def test_decoding_a_restored_response_writes_no_value(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    written_once(tmp_path / "p.db")
    store = SqliteStore.open(tmp_path / "p.db")
    rows = store.load()
    assert rows is not None
    catalog = Catalog.restore(*rows)
    _ = catalog.resources["r1"].response, catalog.client("d1").query.response
    catalog.add_consumer("r1", "q2", "C")  # dirties the row
    dumped: list[Any] = []
    monkeypatch.setattr(schema, "dumps", dumped.append)
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


def test_a_second_registrar_on_a_backup_in_use_is_refused_and_the_first_keeps_its_catalog(
    tmp_path: Path,
) -> None:
    """Two registrars on one `backup_path` (a copied config, a manager started twice) would
    each restore the other's rows and release what its consumers do not hold *there*:
    the first one's resources vanish from the file, their `unload` never runs."""
    path = tmp_path / "p.db"
    name = unique("P")
    provider = start_provider(name, path)
    consumer = rr.ResourceRegistrar.start(unique("C"))
    second: rr.ResourceRegistrar | None = None
    try:
        held = consumer.call(name, "leaf", {"cmd": "x"}, timeout=5)

        with pytest.raises(rr.ConfigError, match="backup_path"):
            second = rr.ResourceRegistrar.start(
                rr.RegistrarConfig(name=unique("Q"), backup_path=path, save_on_modify=True)
            )

        provider.stop()
        provider = start_provider(name, path)
        assert [held.id] == [q.id for q in provider.server_queries("leaf", timeout=5)]
    finally:
        if second is not None:
            second.stop()
        consumer.stop()
        provider.stop()


def test_a_failed_commit_raises_its_own_error_not_one_from_the_rollback(tmp_path: Path) -> None:
    store, catalog = new_store(tmp_path / "p.db")
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
    store, catalog = new_store(tmp_path / "p.db")
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


def test_changes_staged_for_a_turn_wait_for_its_write_and_go_in_one_transaction() -> None:
    store = FlakyStore(fail=1)
    config = rr.RegistrarConfig(name="x", backup_path="flaky", save_on_modify=True)
    saver = _persistence.Saver(store, config)
    saver.stage(Changes({"r1": None}, {}))
    saver.stage(Changes({"r2": None}, {"d1": None}))
    assert ([], True) == (store.written, saver.pending)  # staged: nothing written yet

    with pytest.raises(rr.CatalogWriteError, match="simulated"):
        saver.write()  # the turn's write fails: all of it stays pending
    saver.write()

    assert [(["r1", "r2"], ["d1"])] == store.written
    assert (False, None) == (saver.pending, saver.failure)


def test_a_store_counts_the_transactions_it_committed(tmp_path: Path) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    try:
        store.load()
        catalog = Catalog()
        catalog.begin_load("r1", "cam", 1)
        catalog.finish_load("r1", "one")
        catalog.add_consumer("r1", "q1", "C")
        store.write(catalog.drain_changes())  # a resource and its consumer: one
        store.write(catalog.drain_changes())  # nothing changed: none
        catalog.add_consumer("r1", "q2", "C")
        store.write(catalog.drain_changes())  # one row: one

        assert 2 == store.commits
    finally:
        store.close(erase=False)


def test_changes_whose_interval_flush_failed_are_written_with_the_next_flush() -> None:
    store = FlakyStore(fail=1)
    saver = _persistence.Saver(store, rr.RegistrarConfig(name="x", backup_path="flaky"))
    saver.changed(Changes({"r1": None}, {}))
    with pytest.raises(rr.CatalogWriteError, match="simulated"):
        saver.flush()
    saver.changed(Changes({"r2": None}, {"d1": None}))
    saver.flush()

    assert [(["r1", "r2"], ["d1"])] == store.written


LEAVES = 8
NESTED = 4
MAX_HELD = 24

# -- the child -------------------------------------------------------------------------------


def worker(names: tuple[str, str], paths: tuple[str, str], seed: int, conn: Any) -> None:
    """Run P and C on the backups and drive random operations until killed."""
    rng = random.Random(seed)  # noqa: S311 - a reproducible workload, not crypto
    # background checkpoints (as with a save_interval) run, and are killed, often
    _persistence.CHECKPOINT_EVERY = 4
    real_open = SqliteStore.open

    def open_in_background(path: Any, **options: Any) -> SqliteStore:
        return real_open(path, **{**options, "background_checkpoints": True})

    SqliteStore.open = open_in_background  # type: ignore[method-assign,assignment]
    checkpoints = 0  # finished in this run; sent with every report, so the parent sees them
    real_checkpoint = _persistence.Checkpointer._checkpoint

    def counted(self: _persistence.Checkpointer, db: Any) -> None:
        nonlocal checkpoints
        before = self.checkpoints
        real_checkpoint(self, db)
        checkpoints += self.checkpoints - before  # a failed one does not count

    _persistence.Checkpointer._checkpoint = counted  # type: ignore[method-assign]
    p_name, _ = names
    _, consumer = start_pair(names, paths)
    held = [c.query.id for c in catalog_snapshot(consumer).clients if c.parent is None and c.loaded]
    while True:
        if held and (len(held) >= MAX_HELD or rng.random() < 0.45):
            query_id = held.pop(rng.randrange(len(held)))
            conn.send(("unload-start", query_id, checkpoints))
            with contextlib.suppress(rr.UnknownQueryError):  # released while a run died
                consumer.unload(query_id)
            conn.send(("unload", query_id, checkpoints))
        elif rng.random() < 0.3:
            query = consumer.call(p_name, "nested", rng.randrange(NESTED))
            held.append(query.id)
            conn.send(("load", query.id, checkpoints))
        else:
            query = consumer.call(p_name, "leaf", {"n": rng.randrange(LEAVES)})
            held.append(query.id)
            conn.send(("load", query.id, checkpoints))


# -- the parent ------------------------------------------------------------------------------


@dataclasses.dataclass
class Model:
    """What the child acknowledged, over all its runs."""

    loaded: set[str] = dataclasses.field(default_factory=set)
    unload_started: set[str] = dataclasses.field(default_factory=set)
    unloaded: set[str] = dataclasses.field(default_factory=set)
    checkpoints: int = 0
    """Background checkpoints the runs reported as finished before their last report."""
    _in_run: int = 0

    def record(self, event: str, query_id: str, checkpoints: int) -> None:
        {"load": self.loaded, "unload-start": self.unload_started, "unload": self.unloaded}[
            event
        ].add(query_id)
        self._in_run = max(self._in_run, checkpoints)

    def end_run(self) -> None:
        self.checkpoints += self._in_run
        self._in_run = 0


def restored(path: Path) -> Catalog:
    """Open a backup as a fresh registrar would, and check the catalog's invariants."""
    store = SqliteStore.open(path)
    try:
        rows = store.load()
    finally:
        store.close(erase=False)
    catalog = Catalog.restore(*rows) if rows is not None else Catalog()
    catalog.check_invariants()
    return catalog


def check(paths: tuple[Path, Path], model: Model) -> None:
    """The invariants and the acknowledged operations, on the backups just left behind."""
    provider, consumer = restored(paths[0]), restored(paths[1])
    served = {q for r in provider.resources.values() for q in r.consumers}
    held = {record.query.id for record in consumer.client_records() if record.loaded}
    present = model.loaded - model.unload_started
    assert set() == present - served, "an acknowledged load is missing at the provider"
    assert set() == present - held, "an acknowledged load is missing at the consumer"
    assert set() == model.unloaded & served, "an acknowledged unload is back at the provider"
    held_any = {record.query.id for record in consumer.client_records()}
    assert set() == model.unloaded & held_any, "an acknowledged unload is back"


def run_kills(
    context: multiprocessing.context.BaseContext,
    directory: Path,
    *,
    kills: int,
    seed: int,
    max_reports: int = 30,
) -> Model:
    """Start, drive and SIGKILL the worker `kills` times on one pair of backups.

    Returns the model of what was acknowledged (the checks ran after every kill).
    """
    rng = random.Random(seed)  # noqa: S311 - reproducible kill moments
    names, paths = pair_backups(directory)
    model = Model()
    for _ in range(kills):
        parent_end, child_end = context.Pipe(duplex=False)
        process = context.Process(
            target=worker,
            args=(names, tuple(map(str, paths)), rng.randrange(2**32), child_end),
            daemon=True,
        )
        process.start()
        child_end.close()
        try:
            for _ in range(rng.randrange(max_reports + 1)):
                if not parent_end.poll(20):
                    break
                model.record(*parent_end.recv())
        finally:
            assert process.pid is not None
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid, signal.SIGKILL)
            process.join(10)
        with contextlib.suppress(EOFError, OSError):
            while parent_end.poll(0):  # sent before the kill: acknowledged too
                model.record(*parent_end.recv())
        parent_end.close()
        model.end_run()
        assert process.exitcode == -signal.SIGKILL, f"the worker ended with {process.exitcode}"
        check(paths, model)
    return model


class TestCrashConsistency:
    """Crash consistency: SIGKILL a provider and a consumer at random moments, check the backups.

    A child process (forkserver context) runs a provider registrar `P` and a consumer `C`, both
    with `save_on_modify=True`, and drives random loads, duplicate loads, nested loads and
    unloads, reporting every acknowledged operation to the parent over a pipe. The parent
    kills it after a random number of reports, then opens both backups afresh and checks:

    * each catalog's invariants (`Catalog.check_invariants`);
    * every acknowledged load whose unload was not started is in both catalogs;
    * every acknowledged unload is in neither.

    The next child restarts on the same backups (so restore, in-doubt settling and unloads of
    ids issued before a crash are exercised too). The child's stores checkpoint their WAL
    on a background thread every few statements, so kills also land in checkpoints (each
    report carries how many had finished, and the test checks that they ran).
    `run_kills` is shared with `benchmarks/stress_crash.py`, which runs 1,000 kills.
    """

    # a hang ceiling: a child starts by a fork of the preloading server (`context`), ~0.5 s
    # a kill at load 16; it took ~5 s when each child imported the registrar, and 50 kills
    # went over this ceiling at load 14
    @pytest.mark.timeout(300)
    def test_fifty_random_kills_never_tear_a_catalog_nor_lose_an_acknowledged_operation(
        self, tmp_path: Path, context: multiprocessing.context.ForkServerContext
    ) -> None:
        model = run_kills(context, tmp_path, kills=50, seed=20240613)

        assert model.loaded, "the workload acknowledged no load at all"
        assert model.checkpoints >= 10, "the kills never met background checkpoints"

    def test_a_fresh_registrar_restores_the_backups_left_by_random_kills(
        self, tmp_path: Path, context: multiprocessing.context.ForkServerContext
    ) -> None:
        model = run_kills(context, tmp_path, kills=5, seed=7)
        provider = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=f"P-{uuid.uuid4().hex[:8]}", backup_path=tmp_path / "p.db")
        )
        try:
            view = catalog_snapshot(provider)
        finally:
            provider.stop()

        served = {q for r in view.resources for q in r.consumers}
        assert set() == (model.loaded - model.unload_started) - served


# -- store: every catalog change is one transaction --------------------------------------------


class FailsOnSecondInsert:
    """A connection whose second INSERT fails (an I/O error in the middle of a write)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self.db = db
        self.inserts = 0

    @property
    def in_transaction(self) -> bool:
        return self.db.in_transaction

    def execute(self, sql: str, *args: Any) -> Any:
        if sql.startswith("INSERT"):
            self.inserts += 1
            if self.inserts == 2:
                raise sqlite3.OperationalError("disk I/O error (simulated)")
        return self.db.execute(sql, *args)

    def close(self) -> None:
        self.db.close()


def test_a_write_that_fails_half_way_leaves_none_of_its_statements_in_the_file(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    store, catalog = new_store(path)
    catalog.begin_load("r1", "leaf", {"n": 1})
    catalog.finish_load("r1", {"pid": 1})
    catalog.add_consumer("r1", "q1", "C")
    catalog.add_consumer("r1", "q2", "C")  # one change of three statements
    store._db = FailsOnSecondInsert(store._db)  # type: ignore[assignment]
    try:
        with pytest.raises(rr.CatalogWriteError, match="simulated"):
            store.write(catalog.drain_changes())
    finally:
        store.close(erase=False)

    assert ([], []) == (read_backup(path).resources, read_backup(path).clients)


# -- a backup with a damaged page is never written to (issue 51, finding 4) ----------------------


def write_entries(path: Path, count: int) -> None:
    """A closed backup of `count` loaded resources of server `leaf`, each held by one id of
    registrar `C` (`{"n": i}`, about 300 bytes a row: a page holds about a dozen)."""
    store, catalog = new_store(path)
    for i in range(count):
        catalog.begin_load(f"r{i}", "leaf", {"n": i})
        catalog.finish_load(f"r{i}", {"of": i, "pad": "x" * 200})
        catalog.add_consumer(f"r{i}", f"q{i}", "C")
    store.write(catalog.drain_changes())
    store.close(erase=False)


def damage_a_page_of_resources(path: Path) -> None:
    """Overwrite (with zeros) the middle one of the pages that hold resource rows."""
    with read_only(path, tidy=True) as db:
        size = db.execute("PRAGMA page_size").fetchone()[0]
        try:
            pages = db.execute(
                "SELECT pageno FROM dbstat WHERE name = 'resources' AND pagetype = 'leaf' "
                "ORDER BY pageno"
            ).fetchall()
        except sqlite3.OperationalError:
            pytest.skip("this SQLite has no dbstat table")
    (page,) = pages[len(pages) // 2]
    with path.open("r+b") as file:
        file.seek((page - 1) * size)
        file.write(bytes(size))


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def outcome(call: Any) -> str:
    """What `call()` did: `ok`, or the error, with whether a write error says why."""
    try:
        call()
    except rr.CatalogWriteError as exc:
        return "CatalogWriteError: damaged" if "damaged" in exc.cause else "CatalogWriteError"
    except rr.RrError as exc:
        return type(exc).__name__
    return "ok"


def run_on(path: Path, count: int) -> tuple[set[str], str, str, str]:
    """Start a provider on `path` (`save_on_modify`), call each of its `count` requests again
    from a consumer, list them both ways, stop it: what each did."""
    name = unique("P")
    provider = start_provider(name, path)
    consumer = rr.ResourceRegistrar.start(unique("C"))
    try:
        calls = {outcome(lambda i=i: consumer.call(name, "leaf", {"n": i})) for i in range(count)}
        listed = outcome(lambda: provider.server_queries("leaf"))
        fetched = outcome(lambda: consumer.fetch_queries(name, "leaf"))
    finally:
        consumer.stop()
        stopped = outcome(provider.stop)
    return calls, listed, fetched, stopped


def test_a_registrar_never_writes_to_a_backup_found_with_a_damaged_page(tmp_path: Path) -> None:
    """The lazy restore starts on it (the damaged page is not read before it serves); the
    first write checks every page first, finds the damage and writes nothing: every change
    is refused (`CatalogWriteError` saying the file is damaged; `CatalogCorruptError` for
    the ids on the damaged page), a listing that needs the damaged rows raises
    `CatalogCorruptError` (exact or not at all, rule 10), `stop()` does not raise, and the
    file is byte for byte what it was, at the next start too."""
    path = tmp_path / "p.db"
    write_entries(path, 300)
    damage_a_page_of_resources(path)
    before = sha256(path)

    first = run_on(path, 300)
    second = run_on(path, 300)

    expected = (
        {"CatalogCorruptError", "CatalogWriteError: damaged"},
        "CatalogCorruptError",
        "CatalogCorruptError",
        "ok",
    )
    assert (expected, expected, before) == (first, second, sha256(path))


def test_a_registrar_that_erases_on_destruct_keeps_a_backup_found_damaged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """`erase_on_destruct` does not delete a backup found damaged: it is kept for analysis
    (errors.md), byte for byte, and the stop says so (ERROR) rather than raising."""
    path = tmp_path / "p.db"
    write_entries(path, 300)
    damage_a_page_of_resources(path)
    before = sha256(path)
    name = unique("P")
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=name, backup_path=path, save_on_modify=True, erase_on_destruct=True)
    )
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    consumer = rr.ResourceRegistrar.start(unique("C"))
    try:
        called = outcome(lambda: consumer.call(name, "leaf", {"fresh": 1}))
    finally:
        consumer.stop()
        with caplog.at_level("ERROR", logger="rr_actors"):
            stopped = outcome(provider.stop)

    kept = [r for r in caplog.records if "kept" in r.getMessage()]
    assert ("CatalogWriteError: damaged", "ok", True, before, 1) == (
        called,
        stopped,
        path.exists(),
        sha256(path) if path.exists() else None,
        len(kept),
    )


def test_a_store_that_found_its_file_damaged_refuses_every_write_and_closes_quietly(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_entries(path, 300)
    damage_a_page_of_resources(path)
    before = sha256(path)
    store = SqliteStore.open(path)
    restored = store.restore()
    assert restored is not None
    catalog = Catalog.restore(restored.resources, restored.clients, restored.unread)
    catalog.begin_load("new", "leaf", "new")

    with pytest.raises(rr.CatalogWriteError, match="damaged") as refused:
        store.write(catalog.drain_changes())
    store.close(erase=False)

    assert (rr.CatalogCorruptError, str(path), before) == (
        type(refused.value.__cause__),
        refused.value.path,
        sha256(path),
    )


def leaf_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("leaf", load=leaf_load, unload=noop_unload)


@pytest.mark.usefixtures("process_helpers")  # the forkserver, before the leak check
@pytest.mark.timeout(240)
def test_a_supervised_manager_process_never_writes_to_its_backup_with_a_damaged_page(
    supervisors: Any, uid: str, tmp_path: Path
) -> None:
    """The finding as it was seen: a tree starts on the damaged backup (its manager in its
    own process), the errors reach the caller in another process, the manager keeps
    running (no restart) and the tree's stop raises nothing; the file is as it was."""
    name = f"p-{uid}"
    path = tmp_path / f"{name}.db"
    write_entries(path, 300)
    damage_a_page_of_resources(path)
    before = sha256(path)
    spec = rr.ManagerSpec(name, leaf_setup, isolation="process", start_timeout=120.0)
    sup = supervisors([spec], state_dir=tmp_path).start()
    app = sup.registrar("app")

    calls = {
        outcome(lambda i=i: app.call(name, "leaf", {"n": i}, timeout=60.0)) for i in range(300)
    }
    fetched = outcome(lambda: app.fetch_queries(name, "leaf", timeout=60.0))
    child = sup.child(name)
    stopped = outcome(sup.stop)

    assert (
        {"CatalogCorruptError", "CatalogWriteError: damaged"},
        "CatalogCorruptError",
        ("running", 0),
        "ok",
        before,
    ) == (calls, fetched, (child.state, child.restarts), stopped, sha256(path))


# -- durability: what is synced before an answer leaves (rule 14) ---------------------------

REPLIES = 20  # loads, then as many unloads, at a process manager (two commits each)


@pytest.mark.timeout(300)
def test_with_power_every_answer_leaves_after_the_fdatasync_of_the_log_and_count_it_wrote(
    tmp_path: Path,
) -> None:
    """Traced with strace (every process of the tree): each send of the manager process
    comes after the fdatasync of every write to its backup's file, -wal and -commits, and
    after the sync of the directory each of them was made in (the backup's, its log's
    and its count's names: three, before the marks; the power cut itself:
    `test_with_power_every_answered_change_survives_a_power_cut_...` below)."""
    found = traced(tmp_path, "power", REPLIES)

    assert ([], True, True, 3) == (
        found.unsynced_sends,
        found.syncs_of.get("erm.db-wal", 0) >= 2 * REPLIES,
        found.syncs_of.get("erm.db-commits", 0) >= 2 * REPLIES,
        found.syncs_of_all.get("(directory)", 0),
    )


@pytest.mark.timeout(300)
def test_with_process_durability_nothing_is_synced_and_answers_leave_before_the_disk_has_them(
    tmp_path: Path,
) -> None:
    """The contrast (and the proof that the check above can fail): with the default level,
    no fsync between the first load and the last unload, and the answers leave with the
    log's writes in the page cache only."""
    found = traced(tmp_path, "process", REPLIES)

    assert (0, True) == (found.syncs, len(found.unsynced_sends) >= 2 * REPLIES)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("durability", ["process", "power"])
def test_a_manager_started_on_a_fresh_state_dir_syncs_its_new_backup_and_name_with_power_only(
    tmp_path: Path, durability: str
) -> None:
    """Traced with strace (every process of the tree), `start()` of one process manager on
    a fresh `state_dir`: with power, the new file, then its directory (two); with process,
    nothing (SQLite's own syncs come with the first commit, not with the file)."""
    found = started(tmp_path, durability)

    synced = sorted(
        "(directory)" if name == "(directory)" else name.rsplit(".", 1)[-1]
        for name, count in found.syncs_of.items()
        for _ in range(count)
    )
    assert synced == (["(directory)", "creating"] if durability == "power" else [])


CHANGES = [("load", i) for i in range(6)] + [("unload", i) for i in range(3)]


def power_cut_losses(tmp_path: Path, durability: str) -> tuple[int, list[str]]:
    """A tree (`durability`) whose process manager keeps its backup on ext4 over a logged
    disk; its consumer loads six resources and releases three, one after the other, each
    answer marked in the disk's log. Replayed to each flush after the first mark: the
    flushes checked, and what an acknowledged change lacked there."""
    changes = CHANGES
    with logged_disk(tmp_path) as disk:
        state = disk.mounted / "state"
        spec = rr.ManagerSpec("erm", leaf_setup, isolation="process", heartbeat=None)
        with rr.Supervisor([spec], state_dir=state, durability=durability) as sup:  # type: ignore[arg-type]
            app = sup.registrar("app")
            disk.mark("start")
            ids = []
            for index, (kind, n) in enumerate(changes):
                if kind == "load":
                    ids.append(app.call("erm", "leaf", {"n": n}, timeout=60.0).id)
                else:
                    app.unload(ids[n], timeout=60.0)
                disk.mark(str(index))
            log = disk.dump(tmp_path / "log.pickle")
    checked, lacking = 0, []
    for at, image, marks in flush_points(log, disk.size, "start"):
        done = sorted(int(mark) for mark in marks - {"start"})
        under_way = done[-1] + 1 if done else 0  # (issued, not answered: either state)
        with mounted_image(image) as mounted:
            backup = mounted / "state" / "erm.db"
            lost = lost_commits(backup) if backup.exists() else None
            held = (
                {q for r in read_backup(backup).resources for q in r.consumers} if done else set()
            )
        checked += 1
        if lost is not None:
            lacking.append(f"flush {at}: reported lost: {lost}")
        for index in done:
            kind, n = changes[index]
            released = (index_of := changes.index(("unload", n)) if n < 3 else None) is not None
            released = released and (index_of in done or index_of == under_way)
            if kind == "load" and not released and ids[n] not in held:
                lacking.append(f"flush {at}: load {n} (answered at mark {index}) is missing")
            if kind == "unload" and ids[n] in held:
                lacking.append(f"flush {at}: unload {n} (answered at mark {index}) is undone")
    return checked, lacking


needs_root = pytest.mark.skipif(
    os.geteuid() != 0, reason="a power cut is replayed on a loop device and mounts (root)"
)


@needs_root
@pytest.mark.timeout(600)
def test_with_power_every_answered_change_survives_a_power_cut_at_every_flush_after_it(
    tmp_path: Path,
) -> None:
    checked, lacking = power_cut_losses(tmp_path, "power")

    assert ([], True) == (lacking, checked >= len(CHANGES))


@needs_root
@pytest.mark.timeout(600)
def test_with_process_durability_a_power_cut_loses_answered_changes(tmp_path: Path) -> None:
    """The contrast, and the proof that the replay above can fail: nothing is flushed
    after the loads' answers, so a cut after them may leave the disk without them."""
    _, lacking = power_cut_losses(tmp_path, "process")

    assert [] != [line for line in lacking if "is missing" in line]


# -- the background checkpointer -------------------------------------------------------------------
# A registrar that flushes in bursts checkpoints its WAL on a thread, never in a flush.
#
# SQLite's automatic checkpoint copies the log into the database file inside whichever
# commit crosses its threshold; a store opened with `background_checkpoints` (what a
# registrar with a `save_interval` opens) switches it off and wakes a checkpointer thread
# instead (`rr_actors._store.saver.Checkpointer`). These tests pin that it runs, that
# it keeps the WAL bounded when a reader holds it back, that it stops with the store, that a
# store that writes little never starts it, and which registrars use it. (Crashes in the middle of a
# checkpoint are covered by the crash consistency tests of tests/store/test_saver.py, whose child
# checkpoints in the background every few statements.)


def checkpointer_thread(store: SqliteStore) -> threading.Thread | None:
    assert store._checkpointer is not None
    return store._checkpointer._thread


def write_changes(store: SqliteStore, catalog: Catalog, count: int) -> None:
    """`count` one-statement changes: consumer ids added to one loaded resource."""
    rid = next(iter(catalog.resources))
    for _ in range(count):
        catalog.add_consumer(rid, str(uuid.uuid4()), "C")
        store.write(catalog.drain_changes())


def reader_on_old_snapshot(path: Path) -> sqlite3.Connection:
    """A connection in a read transaction: the WAL cannot be copied past its snapshot."""
    reader = sqlite3.connect(path, isolation_level=None)
    reader.execute("BEGIN")
    reader.execute("SELECT count(*) FROM consumers").fetchone()
    return reader


@pytest.fixture
def held_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[SqliteStore, Catalog, sqlite3.Connection]]:
    """A store at tmp_path/c.db whose log limit is 4 pages, and a reader on an old snapshot
    of it (`rr-actors inspect` on the live file, say); both closed after the test."""
    monkeypatch.setattr(_persistence, "WAL_LIMIT", 4)
    store, catalog = opened(tmp_path / "c.db")
    reader = reader_on_old_snapshot(tmp_path / "c.db")
    yield store, catalog, reader
    reader.close()
    store.close(erase=False)


def wait_checkpoints(store: SqliteStore, count: int, within: float = WAIT) -> tuple[int, int, int]:
    assert store._checkpointer is not None
    done = store._checkpointer.done
    with done:
        assert done.wait_for(lambda: store._checkpointer.checkpoints >= count, within)
        last = store._checkpointer.last
    assert last is not None
    return last


def test_the_writer_never_checkpoints_and_a_thread_copies_the_log(tmp_path: Path) -> None:
    store, catalog = opened(tmp_path / "c.db")
    try:
        assert store._db.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == 0
        store.checkpoint_every = 8
        store._unchecked = 0  # the 8th change, and no later one, wakes it
        write_changes(store, catalog, 8)
        busy, log, copied = wait_checkpoints(store, 1)
        assert busy == 0
        assert 0 < copied == log  # the whole log is in the database file now
        assert store._checkpointer is not None
        assert store._checkpointer.wait_idle(WAIT)
        thread = checkpointer_thread(store)
        assert thread is not None
        assert thread.is_alive()
    finally:
        store.close(erase=False)
    assert not thread.is_alive()  # close stops it
    db = sqlite3.connect(tmp_path / "c.db")
    assert db.execute("SELECT count(*) FROM consumers").fetchone()[0] == 8
    db.close()


def test_a_store_that_writes_little_has_no_checkpointer_thread(tmp_path: Path) -> None:
    store, catalog = opened(tmp_path / "c.db")
    try:
        write_changes(store, catalog, 10)
        assert checkpointer_thread(store) is None
    finally:
        store.close(erase=False)


def test_a_log_held_back_by_a_reader_is_restarted_once_it_passes_the_limit(
    tmp_path: Path, held_back: tuple[SqliteStore, Catalog, sqlite3.Connection]
) -> None:
    store, catalog, reader = held_back
    checkpoint = sqlite3.connect(tmp_path / "c.db", isolation_level=None, timeout=0.05)
    try:
        write_changes(store, catalog, 20)
        store._checkpointer._checkpoint(checkpoint)
        busy, log, copied = store._checkpointer.last or (0, 0, 0)
        # the passive copy stopped at the reader; the RESTART that followed waited for it
        assert (busy, copied < log) == (1, True)
        assert log > 4
        reader.execute("COMMIT")
        store._checkpointer._checkpoint(checkpoint)
        busy, log, copied = store._checkpointer.last or (1, 0, 0)
        assert busy == 0
        assert copied == log
        write_changes(store, catalog, 1)  # the next commit starts the log from its beginning
        assert store._db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()[1] <= 2
    finally:
        checkpoint.close()


def test_without_a_thread_the_writer_falls_back_to_sqlites_own_checkpoints(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_thread(self: threading.Thread) -> None:
        raise RuntimeError("can't start new thread")

    store, catalog = opened(tmp_path / "c.db")
    try:
        store.checkpoint_every = 4
        monkeypatch.setattr(threading.Thread, "start", no_thread)
        write_changes(store, catalog, 4)
        monkeypatch.undo()
        assert store._db.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == 1000
        assert store._checkpointer is None  # SQLite's own from now on: no second try
        write_changes(store, catalog, 4)  # and the writes go on
    finally:
        store.close(erase=False)


@pytest.mark.parametrize(("save_on_modify", "background"), [(False, True), (True, False)])
def test_a_registrar_checkpoints_in_the_background_only_when_it_flushes_in_bursts(
    tmp_path: Path, save_on_modify: bool, background: bool
) -> None:
    config = rr.RegistrarConfig(
        name="R", backup_path=tmp_path / "c.db", save_on_modify=save_on_modify
    )
    store = open_store(config)
    assert isinstance(store, SqliteStore)
    try:
        assert (store._checkpointer is not None) is background
        expected = 0 if background else 1000  # SQLite's own threshold, in pages
        assert store._db.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == expected
    finally:
        store.close(erase=False)


def test_a_checkpointer_that_cannot_open_its_connection_hands_back_to_sqlite(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_connect = sqlite3.connect

    def connect(database: object, *args: object, **kwargs: object) -> sqlite3.Connection:
        if "mode=rw" in str(database):  # the checkpointer's connection only
            raise sqlite3.OperationalError("unable to open database file")
        return real_connect(database, *args, **kwargs)  # type: ignore[arg-type]

    store, catalog = opened(tmp_path / "c.db")
    try:
        store.checkpoint_every = 4
        store._unchecked = 0
        monkeypatch.setattr(sqlite3, "connect", connect)
        write_changes(store, catalog, 4)  # starts the thread, which gives up at once
        thread = checkpointer_thread(store)
        assert thread is not None
        thread.join(WAIT)
        assert not thread.is_alive()
        write_changes(store, catalog, 4)  # the next wake-up finds no thread: SQLite's own
        assert store._checkpointer is None
        assert store._db.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == 1000
    finally:
        store.close(erase=False)


def test_a_relative_backup_path_is_checkpointed_after_a_chdir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path)
    store, catalog = opened(Path("c.db"))
    try:
        monkeypatch.chdir(tmp_path / "elsewhere")  # before the thread first connects
        store.checkpoint_every = 4
        store._unchecked = 0
        write_changes(store, catalog, 4)
        busy, log, copied = wait_checkpoints(store, 1)
        assert (busy, copied == log) == (0, True)
        assert log > 0  # the backup's own WAL, not a new empty file's (-1)
        assert list((tmp_path / "elsewhere").iterdir()) == []
    finally:
        store.close(erase=False)


def test_a_reader_that_lingers_past_the_limit_never_locks_the_writer_out(
    held_back: tuple[SqliteStore, Catalog, sqlite3.Connection],
) -> None:
    # RESTART holds new writes back while it waits for readers: it must give up long
    # before the writer's own busy timeout (5 s), or the writer fails "database is locked"
    store, catalog, _ = held_back
    store.checkpoint_every = 8
    store._unchecked = 0
    write_changes(store, catalog, 8)
    busy, log, copied = wait_checkpoints(store, 1, within=2.5)  # gave up on the reader
    assert (busy, copied < log) == (1, True)
    write_changes(store, catalog, 3)  # and the writer goes on


def test_a_large_response_counts_for_the_pages_it_fills(tmp_path: Path) -> None:
    store, catalog = opened(tmp_path / "c.db")
    try:
        store.checkpoint_every = 8
        store._unchecked = 0
        catalog.begin_load("big", "leaf", {"n": 2})
        catalog.finish_load("big", b"x" * (64 * 1024))  # 16 pages, in one statement or two
        store.write(catalog.drain_changes())
        wait_checkpoints(store, 1)
    finally:
        store.close(erase=False)


# -- background checkpoints: PASSIVE below the limit --------------------------------------------


def test_below_the_limit_a_checkpoint_is_passive_and_does_not_wait_for_a_reader(
    tmp_path: Path,
) -> None:
    path = tmp_path / "c.db"
    store, catalog = opened(path)
    reader = reader_on_old_snapshot(path)
    checkpoint = sqlite3.connect(path, isolation_level=None, timeout=0.05)
    try:
        write_changes(store, catalog, 20)
        assert store._checkpointer is not None
        store._checkpointer._checkpoint(checkpoint)
        last = store._checkpointer.last
    finally:
        checkpoint.close()
        reader.close()
        store.close(erase=False)

    assert last is not None
    busy, log, copied = last
    # PASSIVE copies what it can and reports no wait; any other mode waits and says busy
    assert (busy, log < _persistence.WAL_LIMIT, copied < log) == (0, True, True)


# -- a real bug: a kill in the middle of a growing checkpoint ---------------------------------


def test_a_kill_in_the_middle_of_a_checkpoint_that_grows_the_file_is_not_truncation(
    tmp_path: Path,
) -> None:
    live, crashed = tmp_path / "live.db", tmp_path / "crashed.db"
    store = SqliteStore.open(live)
    try:
        store.load()
        catalog = Catalog()
        for n in range(200):  # the catalog grows by some 25 pages, all of them in the -wal
            catalog.begin_load(f"r{n}", "leaf", {"n": n, "pad": "x" * 300})
            catalog.finish_load(f"r{n}", n)
            catalog.add_consumer(f"r{n}", f"q{n}", "C")
        store.write(catalog.drain_changes())
        before = {s: Path(f"{live}{s}").read_bytes() for s in ("", "-wal", "-shm")}
        # A checkpoint copies the log's pages in page order: page 1 (the header, with the
        # new page count) first. SIGKILL before the last new page is written leaves the
        # old file with the new header, next to the whole -wal:
        store._db.execute("PRAGMA wal_checkpoint(PASSIVE)")
        header_page = live.read_bytes()[:4096]
    finally:
        store.close(erase=False)
    crashed.write_bytes(header_page + before[""][4096:])
    Path(f"{crashed}-wal").write_bytes(before["-wal"])
    Path(f"{crashed}-shm").write_bytes(before["-shm"])

    SqliteStore.open(crashed).close(erase=False)  # not "truncated": SQLite recovers it

    assert {f"q{n}" for n in range(200)} == consumer_ids(crashed)
