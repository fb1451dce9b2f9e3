"""A registrar that flushes in bursts checkpoints its WAL on a thread, never in a flush.

SQLite's automatic checkpoint copies the log into the database file inside whichever
commit crosses its threshold; a store opened with `background_checkpoints` (what a
registrar with a `save_interval` opens) switches it off and wakes a checkpointer thread
instead (`rr_actors._store.checkpoints.Checkpointer`). These tests pin that it runs, that
it keeps the WAL bounded when a reader holds it back, that it stops with the store, that a
store that writes little never starts it, and which registrars use it. (Crashes in the middle of a
checkpoint are covered by the crash consistency tests of tests/store/test_sqlite.py, whose child
checkpoints in the background every few statements.)
"""

from __future__ import annotations

import sqlite3
import threading
import uuid
from pathlib import Path

import pytest

import rr_actors as rr
from rr_actors._catalog import Catalog
from rr_actors._store import checkpoints
from rr_actors._store.saver import open_store
from rr_actors._store.sqlite import SqliteStore
from tests.support.durable_pair import opened
from tests.support.persisting import consumer_ids

WAIT = 10.0  # seconds: the bound of every wait below


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
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(checkpoints, "WAL_LIMIT", 4)
    path = tmp_path / "c.db"
    store, catalog = opened(path)
    reader = reader_on_old_snapshot(path)
    checkpoint = sqlite3.connect(path, isolation_level=None, timeout=0.05)
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
        reader.close()
        store.close(erase=False)


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
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # RESTART holds new writes back while it waits for readers: it must give up long
    # before the writer's own busy timeout (5 s), or the writer fails "database is locked"
    monkeypatch.setattr(checkpoints, "WAL_LIMIT", 4)
    path = tmp_path / "c.db"
    store, catalog = opened(path)
    reader = reader_on_old_snapshot(path)  # `rr-actors inspect` on the live file, say
    try:
        store.checkpoint_every = 8
        store._unchecked = 0
        write_changes(store, catalog, 8)
        busy, log, copied = wait_checkpoints(store, 1, within=2.5)  # gave up on the reader
        assert (busy, copied < log) == (1, True)
        write_changes(store, catalog, 3)  # and the writer goes on
    finally:
        reader.close()
        store.close(erase=False)


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
    reader = sqlite3.connect(path, isolation_level=None)
    reader.execute("BEGIN")
    reader.execute("SELECT count(*) FROM consumers").fetchone()  # an old snapshot
    checkpoint = sqlite3.connect(path, isolation_level=None, timeout=0.05)
    try:
        for _ in range(20):
            catalog.add_consumer("r1", str(uuid.uuid4()), "C")
            store.write(catalog.drain_changes())
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
    assert (busy, log < checkpoints.WAL_LIMIT, copied < log) == (0, True, True)


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
