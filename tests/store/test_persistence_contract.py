"""The durable catalogs' contract (issue 3), clause by clause: what no other test pins.

Each test names the clause it pins. Every wait is bounded and waits on an event, a
future or a condition; a "not yet" check (`assert not answered.wait(...)`) is a bounded
wait on an event that a broken implementation sets at once.
"""

from __future__ import annotations

import collections
import contextlib
import io
import json
import os
import sqlite3
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.__main__ import main
from rr_actors._catalog import Catalog, request_digest
from rr_actors._store import checkpoints, codec, files, schema
from rr_actors._store import saver as _persistence
from rr_actors._store.files import quarantine_backup, read_backup
from rr_actors._store.saver import open_store
from rr_actors._store.sqlite import SqliteStore
from rr_actors.testing import catalog_snapshot, crash
from tests.support.durable_pair import opened, schema_2_database, start

WAIT = 10.0  # seconds: the bound of every wait that must succeed
NOT_YET = 0.5  # seconds a caller must stay unanswered while the backup is locked


def unique(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


def noop_unload(_request: Any, _response: Any) -> None:
    return None


def consumer_ids(path: Path) -> set[str]:
    return {q for r in read_backup(path).resources for q in r.consumers}


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
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
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


# -- store: explicit migrations ---------------------------------------------------------------


def write_v2_backup(path: Path) -> None:
    """A schema-2 backup (rowid consumers, no indexes): r0 loaded with consumer q0."""
    db = schema_2_database(path)
    dumps = codec.dumps
    db.execute(
        "INSERT INTO resources VALUES (1, 'r0', 'leaf', 1, ?, ?, ?)",
        (request_digest({"n": 0}), dumps({"n": 0}), dumps({"pid": 0})),
    )
    db.execute("INSERT INTO consumers VALUES (2, 'q0', 1, 'C')")
    db.execute("PRAGMA journal_mode = WAL")
    db.close()


def test_a_version_2_backup_is_brought_to_the_current_schema_with_its_indexes(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_v2_backup(path)

    SqliteStore.open(path).close(erase=False)

    db = sqlite3.connect(path)
    try:
        version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]
        indexes = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='index'")}
        consumers_pk = [r[1] for r in db.execute("PRAGMA table_info(consumers)") if r[5]]
    finally:
        db.close()
    assert (schema.SCHEMA_VERSION, True, ["resource", "seq"]) == (
        version,
        set(schema.INDEXES) <= indexes,
        consumers_pk,
    )


def test_a_migration_step_that_fails_leaves_the_file_at_its_old_version(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "p.db"
    SqliteStore.open(path).close(erase=False)

    def half_done(db: sqlite3.Connection) -> None:
        db.execute("ALTER TABLE resources ADD COLUMN note TEXT")
        raise sqlite3.OperationalError("disk I/O error (simulated)")

    monkeypatch.setattr(schema, "MIGRATIONS", (*schema.MIGRATIONS, half_done))
    monkeypatch.setattr(schema, "SCHEMA_VERSION", schema.SCHEMA_VERSION + 1)
    with pytest.raises((rr.CatalogCorruptError, sqlite3.Error)):
        SqliteStore.open(path)
    monkeypatch.undo()

    db = sqlite3.connect(path)
    try:
        version = db.execute("SELECT version FROM rr_actors_schema").fetchone()[0]
        columns = [row[1] for row in db.execute("PRAGMA table_info(resources)")]
    finally:
        db.close()
    assert (schema.SCHEMA_VERSION, False) == (version, "note" in columns)


# -- store: a database of another program ------------------------------------------------------


def test_a_database_of_another_program_with_a_schema_table_is_refused_by_application_id(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    SqliteStore.open(path).close(erase=False)  # an rr_actors layout ...
    db = sqlite3.connect(path)
    db.execute("PRAGMA application_id = 1234")  # ... stamped by another program
    db.commit()
    db.close()
    before = path.read_bytes()

    with pytest.raises(rr.CatalogCorruptError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert (str(path), True, before) == (
        raised.value.path,
        "not an rr_actors catalog" in raised.value.cause,
        path.read_bytes(),
    )


# -- bad locations (the suite runs as root, where permissions do not refuse anything) -----------


def test_a_read_only_directory_raises_config_error_naming_the_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_access = os.access
    directory = str(tmp_path)

    def access(path: Any, mode: int, **kwargs: Any) -> bool:
        if os.fspath(path) == directory and mode & os.W_OK:
            return False  # what a non-root user sees for a read-only directory
        return real_access(path, mode, **kwargs)

    monkeypatch.setattr(os, "access", access)
    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=unique("P"), backup_path=tmp_path / "p.db")
        )

    assert (True, True, []) == (
        str(tmp_path / "p.db") in str(raised.value),
        "is not writable" in str(raised.value),
        list(tmp_path.iterdir()),
    )


def test_a_read_only_backup_file_raises_config_error_and_is_left_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "p.db"
    SqliteStore.open(path).close(erase=False)
    before = path.read_bytes()
    real_access = os.access

    def access(where: Any, mode: int, **kwargs: Any) -> bool:
        if os.fspath(where) == str(path) and mode & os.W_OK:
            return False
        return real_access(where, mode, **kwargs)

    monkeypatch.setattr(os, "access", access)
    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert (True, True, before) == (
        str(path) in str(raised.value),
        "not readable and writable" in str(raised.value),
        path.read_bytes(),
    )


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
    real_timer = _persistence.thread_timer

    def observed(delay: float, tick: Callable[[], None]) -> _persistence.Cancellable:
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


# -- in doubt: unloads cut short too -------------------------------------------------------------


def write_unloading(path: Path) -> None:
    """A backup whose resource r-stop was being unloaded when the process died."""
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    catalog.begin_load("r-stop", "start_process", {"cmd": "sleep"})
    catalog.finish_load("r-stop", {"pid": 42})
    catalog.begin_unload("r-stop")
    store.write(catalog.drain_changes())
    store.close(erase=False)


def test_an_unload_cut_short_is_reported_in_doubt_and_dropped(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "p.db"
    write_unloading(path)

    registrar = start(started, unique("P"), path, save_on_modify=True)

    assert [("start_process", {"cmd": "sleep"}, {"pid": 42})] == [
        (q.server, q.request, q.response) for q in registrar.in_doubt
    ]
    assert () == catalog_snapshot(registrar).resources


def run_cli(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    return main(list(argv), out), out.getvalue()


def test_inspect_marks_a_half_unloaded_resource_in_doubt_in_the_tree_and_the_json(
    tmp_path: Path,
) -> None:
    path = tmp_path / "p.db"
    write_unloading(path)

    code, tree = run_cli("inspect", str(path))
    json_code, data = run_cli("inspect", str(path), "--json")

    [line] = [line for line in tree.splitlines() if "r-stop" in line]
    [resource] = json.loads(data)["servers"]["start_process"]
    assert (0, 0, True, True, True) == (
        code,
        json_code,
        "[IN DOUBT: unloading]" in line,
        "1 in doubt" in tree,
        resource["in_doubt"],
    )


def test_inspect_json_marks_a_half_loaded_resource_in_doubt(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    catalog.begin_load("r-loading", "start_process", {"cmd": "sleep"})
    catalog.begin_load("r-fine", "start_process", {"cmd": "true"})
    catalog.finish_load("r-fine", {"pid": 1})
    store.write(catalog.drain_changes())
    store.close(erase=False)

    code, out = run_cli("inspect", str(path), "--json")

    flags = {r["id"]: r["in_doubt"] for r in json.loads(out)["servers"]["start_process"]}
    assert (0, {"r-loading": True, "r-fine": False}) == (code, flags)


# -- inspect reads one consistent snapshot of a live file ---------------------------------------


class WriterBetweenReads:
    """A read connection; right after the resources were read, another connection commits a
    resource with a consumer (what a live registrar may do while `inspect` reads)."""

    def __init__(self, db: sqlite3.Connection, path: Path) -> None:
        self._db = db
        self._path = path
        self.wrote = False

    def execute(self, sql: str, *args: Any) -> Any:
        cursor = self._db.execute(sql, *args)
        if not sql.startswith("SELECT seq, id, server, state") or self.wrote:
            return cursor
        rows = cursor.fetchall()
        self.wrote = True
        writer = sqlite3.connect(self._path, isolation_level=None)
        try:
            writer.execute("BEGIN IMMEDIATE")
            writer.execute(
                "INSERT INTO resources (seq, id, server, state, digest, request, response) "
                "VALUES (50, 'r-new', 'leaf', 1, ?, ?, NULL)",
                (request_digest(2), codec.dumps(2)),
            )
            writer.execute("INSERT INTO consumers VALUES (50, 51, 'q-new', 'C')")
            writer.execute("COMMIT")
        finally:
            writer.close()
        return _Rows(rows)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)


class _Rows:
    def __init__(self, rows: list[Any]) -> None:
        self._rows = rows

    def fetchall(self) -> list[Any]:
        return self._rows


def test_inspect_reads_one_snapshot_while_a_registrar_commits(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "p.db"
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", 1)
    catalog.finish_load("r1", 1)
    catalog.add_consumer("r1", "q1", "C")
    store.write(catalog.drain_changes())  # the live registrar keeps its store open
    real_connect = files.connect
    wrappers: list[WriterBetweenReads] = []

    def connect(where: Path, *, read_only: bool) -> Any:
        db = real_connect(where, read_only=read_only)
        if not read_only:
            return db
        wrapper = WriterBetweenReads(db, path)
        wrappers.append(wrapper)
        return wrapper

    monkeypatch.setattr(files, "connect", connect)
    try:
        backup = read_backup(path)
    finally:
        monkeypatch.undo()
        store.close(erase=False)

    assert any(w.wrote for w in wrappers)
    assert [("r1", ["q1"])] == [(r.id, list(r.consumers)) for r in backup.resources]
    assert {"r1", "r-new"} == {r.id for r in read_backup(path).resources}


# -- quarantine_backup -------------------------------------------------------------------------


def test_quarantine_moves_the_wal_and_shm_files_with_the_backup(tmp_path: Path) -> None:
    live, crashed = tmp_path / "live", tmp_path / "crashed"
    live.mkdir()
    crashed.mkdir()
    store = SqliteStore.open(live / "p.db")
    try:
        store.load()
        catalog = Catalog()
        catalog.begin_load("r1", "leaf", 1)
        catalog.finish_load("r1", 1)
        catalog.add_consumer("r1", "q1", "C")
        store.write(catalog.drain_changes())  # in the -wal only: no checkpoint yet
        for suffix in ("", "-wal", "-shm"):  # the files a killed registrar leaves
            (crashed / f"p.db{suffix}").write_bytes((live / f"p.db{suffix}").read_bytes())
    finally:
        store.close(erase=False)

    moved = quarantine_backup(crashed / "p.db")

    assert (["p.db", "p.db-shm", "p.db-wal"], {"q1"}) == (
        sorted(p.name.replace(moved.name, "p.db") for p in crashed.iterdir()),
        consumer_ids(moved),
    )


def test_quarantining_twice_keeps_both_files(tmp_path: Path) -> None:
    path = tmp_path / "p.db"
    path.write_bytes(b"first garbage" * 100)
    first = quarantine_backup(path)
    path.write_bytes(b"second garbage" * 100)
    second = quarantine_backup(path)

    assert (True, b"first garbage" * 100, b"second garbage" * 100) == (
        first != second,
        first.read_bytes(),
        second.read_bytes(),
    )


# -- requests are stored with cloudpickle ---------------------------------------------------------


def test_a_request_holding_a_function_defined_here_is_stored_and_restored(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    path = tmp_path / "p.db"
    name = unique("P")
    offset = 40

    def local_callback(value: int) -> int:  # not importable by name: plain pickle refuses it
        return value + offset

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=lambda r: r["f"](2), unload=noop_unload)
    query = provider.call(name, "leaf", {"f": local_callback})

    [resource] = read_backup(path).resources
    assert (42, 42, {query.id}) == (query.response, resource.request["f"](2), consumer_ids(path))


def test_an_unhashable_request_without_a_digest_is_found_again_after_a_restart(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    # Counter has its own __eq__ (so no stored digest) and is unhashable: after a restore
    # only `==` against the restored request can find it
    path = tmp_path / "p.db"
    name = unique("P")
    loads: list[Any] = []

    def load(request: Any) -> Any:
        loads.append(request)
        return {"pid": len(loads)}

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=load, unload=noop_unload)
    first = provider.call(name, "leaf", collections.Counter({"cam": 2, "lidar": 1}))
    crash(provider)  # a clean stop would give back the id this registrar holds itself

    provider = start(started, name, path, save_on_modify=True)
    provider.register_server("leaf", load=load, unload=noop_unload)
    again = provider.call(name, "leaf", collections.Counter({"lidar": 1, "cam": 2}))

    assert (1, {"pid": 1}, {first.id, again.id}) == (len(loads), again.response, consumer_ids(path))


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
