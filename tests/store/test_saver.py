"""The save policies: save_on_modify, the save interval, clean stops, erase_on_destruct
(rules 13-14; `_store/saver.py`).
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog
from rr_actors._core import runtime
from rr_actors._store import saver as _persistence
from rr_actors._store import schema
from rr_actors._store.restore import read_backup
from rr_actors._store.saver import open_store
from rr_actors._store.sqlite import SqliteStore
from rr_actors.testing import catalog_snapshot, crash
from tests.support.durable_pair import leaf_load, noop_unload, pair_backups, start
from tests.support.persisting import (
    ManualTimers,
    RunAndKill,
    child_hold,
    consumer_ids,
    unique,
)


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
    from tests.store.test_sqlite import Unwalked  # noqa: PLC0415 - the one walker guard

    store = SqliteStore.open(tmp_path / "p.db")
    saver = _persistence.Saver(store, rr.RegistrarConfig(name=unique("S"), save_on_modify=True))
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", "loaded")
    for n in range(100):
        catalog.add_consumer("r1", f"h{n}", "C")
    saver.stage(catalog.drain_changes())
    saver.write()
    resource = catalog.resources["r1"]
    resource.consumers = Unwalked(resource.consumers)
    statements: list[str] = []
    store._db.set_trace_callback(statements.append)

    catalog.add_consumer("r1", "new", "C")
    saver.stage(catalog.drain_changes())
    catalog.release("h0")
    saver.stage(catalog.drain_changes())
    saver.write()
    saver.close(erase=False)

    assert [
        "BEGIN IMMEDIATE",
        "INSERT INTO consumers (resource, seq, query_id, origin_rr) VALUES (1, 102, 'new', 'C')",
        "DELETE FROM consumers WHERE resource = 1 AND seq = 2",
        "COMMIT",
    ] == statements
