"""The save policies: save_on_modify, the save interval, clean stops, erase_on_destruct
(rules 13-14; `_store/saver.py`).
"""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._store import schema
from rr_actors._store.files import read_backup
from rr_actors._store.sqlite import SqliteStore
from rr_actors.testing import catalog_snapshot, crash
from tests.support.durable_pair import leaf_load, noop_unload, pair_backups, start
from tests.support.persisting import ManualTimers, RunAndKill, child_hold, consumer_ids, unique


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


def test_a_clean_stop_flushes_pending_changes(tmp_path: Path) -> None:
    provider = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=unique("P"), backup_path=tmp_path / "p.db", save_interval=None)
    )
    consumer = rr.ResourceRegistrar.start(unique("C"))
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    query = consumer.call(provider.name, "leaf", 1)

    provider.stop()
    consumer.stop()

    assert {query.id} == consumer_ids(tmp_path / "p.db")


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
