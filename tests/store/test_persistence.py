"""Durable catalogs: the SQLite store, the save policies, restore and bad files (rules 13-16).

Crashes are real: a child process (forkserver context) runs the registrars, reports what
it did over a pipe and is SIGKILLed; the test process then starts fresh registrars on the
same backups. Module-level functions run in the child (sent by reference).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import os
import pickle
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from durable_pair import leaf_load, noop_unload, start, start_consumer, start_pair, start_provider
from hypothesis import given, settings
from hypothesis import strategies as st
from small_disk import mounted, remount_read_only

import rr_actors as rr
from rr_actors._catalog import (
    DIGEST_SCHEME,
    Catalog,
    Changes,
    ClientRecord,
    ResourceState,
    request_digest,
)
from rr_actors._store import codec, schema
from rr_actors._store import saver as _persistence
from rr_actors._store.files import quarantine_backup, read_backup
from rr_actors._store.sqlite import SqliteStore
from rr_actors.testing import catalog_snapshot, crash

# -- what runs in the child process ----------------------------------------------------------


def child_hold(names: tuple[str, str], paths: tuple[str, str], conn: Any) -> None:
    """Provider P and consumer C with backups: load a leaf twice and a nested resource,
    send the ids and both catalogs to the parent, then wait to be killed."""
    p_name, _ = names
    provider, consumer = start_pair(names, paths)
    first = consumer.call(p_name, "leaf", {"a": 1, "b": [1, 2]})
    second = consumer.call(p_name, "leaf", {"b": [1, 2], "a": 1})
    third = consumer.call(p_name, "nested", "x")
    conn.send(
        ((first.id, second.id, third.id), catalog_snapshot(provider), catalog_snapshot(consumer))
    )
    conn.recv()  # never answered: the parent kills this process


def child_stuck_in_load(names: tuple[str, str], paths: tuple[str, str], conn: Any) -> None:
    """A load that loads a dependency, tells the parent, and hangs until it is killed."""
    p_name, c_name = names
    provider = start_provider(p_name, paths[0])

    def stuck(request: Any) -> Any:
        provider.call(p_name, "leaf", {"dependency of": request})
        conn.send("started")
        threading.Event().wait(60)
        return None

    provider.register_server("stuck", load=stuck, unload=noop_unload)
    consumer = start_consumer(c_name, paths[1])
    consumer.call(p_name, "stuck", {"job": 7}, timeout=60)


@pytest.fixture(scope="session")
def context() -> multiprocessing.context.ForkServerContext:
    """The forkserver context, its server started before any leak check."""
    ctx = multiprocessing.get_context("forkserver")
    assert isinstance(ctx, multiprocessing.context.ForkServerContext)
    ctx.set_forkserver_preload(["rr_actors", "rr_actors._store.sqlite", "cloudpickle"])
    multiprocessing.forkserver.ensure_running()
    return ctx


RunAndKill = Callable[..., list[Any]]


@pytest.fixture
def run_and_kill(context: multiprocessing.context.ForkServerContext) -> RunAndKill:
    """`run_and_kill(target, *args, messages=1)`: run `target(*args, conn)` in a child,
    receive `messages` messages from it, SIGKILL it, and return the messages."""

    def run(target: Callable[..., None], *args: Any, messages: int = 1) -> list[Any]:
        parent_end, child_end = context.Pipe()
        process = context.Process(target=target, args=(*args, child_end), daemon=True)
        process.start()
        child_end.close()
        received = []
        try:
            for _ in range(messages):
                assert parent_end.poll(30), "the child did not report in time"
                received.append(parent_end.recv())
        finally:
            assert process.pid is not None
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid, signal.SIGKILL)
            process.join(10)
            parent_end.close()
        assert process.exitcode == -signal.SIGKILL
        return received

    return run


# -- helpers --------------------------------------------------------------------------------


def unique(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


def ordered(view: Any) -> Any:
    """A catalog view as comparable data, with consumer order made visible."""
    return (
        [
            (r.id, r.server, r.request, r.response, r.state, list(r.consumers.items()))
            for r in view.resources
        ],
        [(c.query, c.parent, c.loaded) for c in view.clients],
    )


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


class Recorder:
    """Recording load/unload callbacks for servers registered in the test process."""

    def __init__(self) -> None:
        self.loads: list[Any] = []
        self.unloads: list[Any] = []
        self.unloaded = threading.Event()

    def load(self, request: Any) -> Any:
        self.loads.append(request)
        return {"leaf": request}

    def unload(self, request: Any, _response: Any) -> None:
        self.unloads.append(request)
        self.unloaded.set()


class ManualTimers:
    """A save-interval clock the test advances by hand (`fire()`)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pending: list[tuple[float, Callable[[], None]]] = []
        self.armed = threading.Event()

    def __call__(self, delay: float, tick: Callable[[], None]) -> Any:
        entry = (delay, tick)
        with self.lock:
            self.pending.append(entry)
        self.armed.set()
        timers = self

        class Handle:
            def cancel(self) -> None:
                with timers.lock, contextlib.suppress(ValueError):
                    timers.pending.remove(entry)

        return Handle()

    def fire(self) -> float:
        """Run every pending tick once; return the delay they were armed with."""
        with self.lock:
            due, self.pending = self.pending, []
            self.armed.clear()
        assert due, "no save-interval timer was armed"
        for _, tick in due:
            tick()
        return due[0][0]


@pytest.fixture
def timers(monkeypatch: pytest.MonkeyPatch) -> ManualTimers:
    manual = ManualTimers()
    monkeypatch.setattr(_persistence, "timer_factory", manual)
    return manual


def consumer_ids(path: Path) -> set[str]:
    """Consumer ids stored in a backup, read through a separate connection."""
    return {q for r in read_backup(path).resources for q in r.consumers}


# -- restore after a real crash ---------------------------------------------------------------


def test_a_registrar_restarted_after_a_kill_restores_every_served_query_and_client_record(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    [(_, provider_view, consumer_view)] = run_and_kill(child_hold, names, tuple(map(str, paths)))

    provider = start(started, names[0], paths[0], save_on_modify=True)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)
    provider.register_server("nested", load=leaf_load, unload=noop_unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    assert (True, True) == (provider.restored, consumer.restored)
    assert ordered(provider_view) == ordered(catalog_snapshot(provider))
    assert ordered(consumer_view) == ordered(catalog_snapshot(consumer))


def test_setup_code_sees_the_restored_queries_before_it_registers_its_servers(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    [((first, second, _), _, _)] = run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    provider.register_server("leaf", load=leaf_load, unload=noop_unload)

    held = provider.server_queries("leaf")

    assert {first, second} <= {q.id for q in held}


def test_consumer_ids_issued_before_a_kill_unload_after_the_restart(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    [((first, second, _), _, _)] = run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf = Recorder()
    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)
    provider.register_server("nested", load=leaf.load, unload=noop_unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    consumer.unload(first)
    consumer.unload(second)

    assert [{"a": 1, "b": [1, 2]}] == leaf.unloads


def test_a_nested_resource_restored_after_a_kill_releases_its_dependency_when_unloaded(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    [((_, _, third), _, _)] = run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf, nested = Recorder(), Recorder()
    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)
    provider.register_server("nested", load=nested.load, unload=nested.unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    consumer.unload(third)

    assert ([{"sub": "x"}], ["x"]) == (leaf.unloads, nested.unloads)


def test_an_equal_request_after_a_restart_in_another_process_reuses_the_restored_resource(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    # The child hashed its strings with another seed: only requests are stored, never hashes.
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    run_and_kill(child_hold, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf = Recorder()
    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)
    provider.register_server("nested", load=leaf.load, unload=noop_unload)
    consumer = start(started, names[1], paths[1], save_on_modify=True)

    query = consumer.call(names[0], "leaf", {"b": [1, 2], "a": 1})

    assert ([], {"leaf": {"a": 1, "b": [1, 2]}}) == (leaf.loads, query.response)


# -- in-doubt loads ---------------------------------------------------------------------------


def test_a_load_killed_inside_its_callback_is_reported_in_doubt_after_the_restart(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    run_and_kill(child_stuck_in_load, names, tuple(map(str, paths)))

    provider = start(started, names[0], paths[0], save_on_modify=True)

    assert [("stuck", {"job": 7})] == [(q.server, q.request) for q in provider.in_doubt]


def test_the_dependency_of_an_in_doubt_load_is_released_after_the_restart(
    tmp_path: Path,
    run_and_kill: RunAndKill,
    started: list[rr.ResourceRegistrar],
    eventually: Callable[..., bool],
) -> None:
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    run_and_kill(child_stuck_in_load, names, tuple(map(str, paths)))
    provider = start(started, names[0], paths[0], save_on_modify=True)
    leaf = Recorder()

    provider.register_server("leaf", load=leaf.load, unload=leaf.unload)

    assert leaf.unloaded.wait(5)
    assert eventually(lambda: not catalog_snapshot(provider).resources)
    assert [{"dependency of": {"job": 7}}] == leaf.unloads


def test_a_registrar_without_in_doubt_loads_reports_none(
    tmp_path: Path, run_and_kill: RunAndKill, started: list[rr.ResourceRegistrar]
) -> None:
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")
    run_and_kill(child_hold, names, tuple(map(str, paths)))

    provider = start(started, names[0], paths[0], save_on_modify=True)

    assert () == provider.in_doubt


# -- save policies ----------------------------------------------------------------------------


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
    names, paths = (unique("P"), unique("C")), (tmp_path / "p.db", tmp_path / "c.db")

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


# -- the store on its own ---------------------------------------------------------------------


def make_query(qid: str, request: Any, *, target: str = "P", origin: str = "C") -> rr.Query:
    return rr.Query(qid, "leaf", target, origin, request)


def reopen(path: Path) -> Catalog:
    """Read a backup back, every row at once; the lazy restore must read the same catalog."""
    store = SqliteStore.open(path)
    try:
        rows = store.load()
        assert rows is not None
        catalog = Catalog.restore(*rows)
        catalog.check_invariants()
        lazily = reopen_lazily(path)
        assert shape_of(catalog) == shape_of(lazily)
    finally:
        store.close(erase=False)
    return catalog


def shape_of(catalog: Catalog) -> Any:
    """The rows without their values (a test may store one that cannot be decoded)."""
    return [
        (r.id, r.server, r.state, list(r.consumers.items())) for r in catalog.resources.values()
    ]


def reopen_lazily(path: Path) -> Catalog:
    """Restore a backup as a registrar does (resources read on first use), then read all."""
    store = SqliteStore.open(path)
    try:
        restored = store.restore()
        assert restored is not None
        catalog = Catalog.restore(restored.resources, restored.clients, restored.unread)
        catalog.read_all()
    finally:
        store.close(erase=False)
    return catalog


def rows_of(catalog: Catalog) -> Any:
    return (
        [
            (r.id, r.server, r.request, r.response, r.state, list(r.consumers.items()))
            for r in catalog.resources.values()
        ],
        [(c.query, c.parent, c.loaded) for c in catalog.clients.values()],
    )


def random_load(rng: random.Random, catalog: Catalog) -> None:
    request = {"n": rng.randrange(6), "tags": [rng.randrange(3)]}
    if catalog.find("leaf", request) is None:
        rid = str(uuid.uuid4())
        catalog.begin_load(rid, "leaf", request)
        if rng.random() < 0.8:
            catalog.finish_load(rid, ("pid", rng.randrange(1000)))
            catalog.add_consumer(rid, str(uuid.uuid4()), rng.choice("CD"))


def random_release(rng: random.Random, catalog: Catalog, held: list[str]) -> None:
    resource = catalog.release(rng.choice(held))
    if not resource.consumers:
        catalog.begin_unload(resource.id)
        if rng.random() < 0.7:
            for dep in catalog.dependencies(resource.id):
                catalog.remove_client(dep.query.id)
            catalog.remove_resource(resource.id)


def random_program(rng: random.Random, catalog: Catalog, steps: int) -> Iterator[None]:
    """Apply `steps` random valid catalog changes, yielding after each."""
    for _ in range(steps):
        loaded = [r for r in catalog.resources.values() if r.state is ResourceState.LOADED]
        held = [q for r in loaded for q in r.consumers]
        choice = rng.randrange(8)
        if choice <= 1 or not catalog.resources:
            random_load(rng, catalog)
        elif choice == 2 and loaded:
            catalog.add_consumer(rng.choice(loaded).id, str(uuid.uuid4()), rng.choice("CD"))
        elif choice == 3 and held:
            random_release(rng, catalog, held)
        elif choice == 4 and loaded:
            catalog.set_response(rng.choice(loaded).id, {"new": rng.random()})
        elif choice == 5:
            parent = rng.choice([None, *catalog.resources])
            qid = str(uuid.uuid4())
            catalog.add_client(ClientRecord(make_query(qid, rng.randrange(9)), parent))
        elif choice == 6 and catalog.clients:
            catalog.client_loaded(rng.choice(list(catalog.clients)), rng.randrange(9))
        elif choice == 7 and catalog.clients:
            catalog.remove_client(rng.choice(list(catalog.clients)))
        yield


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


# -- bad files --------------------------------------------------------------------------------


def write_valid_backup(path: Path) -> None:
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    for n in range(300):
        catalog.begin_load(f"r{n}", "leaf", {"n": n, "pad": "x" * 200})
        catalog.finish_load(f"r{n}", n)
        catalog.add_consumer(f"r{n}", f"q{n}", "C")
    store.write(catalog.drain_changes())
    store.close(erase=False)


def make_garbage(path: Path) -> None:
    path.write_bytes(os.urandom(5000))


def make_truncated(path: Path) -> None:
    write_valid_backup(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def make_empty(path: Path) -> None:
    path.write_bytes(b"")


def make_foreign(path: Path) -> None:
    db = sqlite3.connect(path)
    db.execute("CREATE TABLE songs (title TEXT)")
    db.commit()
    db.close()


def make_newer(path: Path) -> None:
    SqliteStore.open(path).close(erase=False)
    db = sqlite3.connect(path)
    db.execute("UPDATE rr_actors_schema SET version = 99")
    db.commit()
    db.close()


def make_bad_row(path: Path) -> None:
    write_valid_backup(path)
    db = sqlite3.connect(path)
    db.execute("UPDATE resources SET request = x'00ff00' WHERE id = 'r7'")
    db.commit()
    db.close()


@pytest.mark.parametrize(
    ("make", "cause"),
    [
        (make_garbage, "not an SQLite database"),
        (make_truncated, "truncated"),
        (make_empty, "empty"),
        (make_foreign, "not an rr_actors catalog"),
        (make_newer, "schema version 99 is newer"),
    ],
)
def test_a_bad_backup_raises_catalog_corrupt_error_naming_the_file_and_is_left_untouched(
    tmp_path: Path, make: Callable[[Path], None], cause: str
) -> None:
    path = tmp_path / "p.db"
    make(path)
    before = digest(path)
    name = unique("P")

    with pytest.raises(rr.CatalogCorruptError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, backup_path=path))

    assert (str(path), True, before, sorted(os.listdir(tmp_path))) == (
        raised.value.path,
        cause in raised.value.cause,
        digest(path),
        ["p.db"],
    )


def test_a_damaged_resource_row_raises_catalog_corrupt_error_when_first_used_and_only_then(
    tmp_path: Path,
) -> None:
    """A restore reads served resources on first use: a damaged one fails that use alone."""
    path = tmp_path / "p.db"
    make_bad_row(path)  # r7's request is not a pickle; r0 .. r299 are fine
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=unique("P"), backup_path=path, save_interval=None)
    )
    try:
        registrar.register_server("leaf", load=lambda r: r, unload=noop_unload)
        seventh, eighth = ({"n": n, "pad": "x" * 200} for n in (7, 8))
        with pytest.raises(rr.CatalogCorruptError) as damaged:
            registrar.call(registrar.name, "leaf", seventh)
        with pytest.raises(rr.CatalogCorruptError) as again:
            registrar.call(registrar.name, "leaf", seventh)
        neighbour = registrar.call(registrar.name, "leaf", eighth)  # r8, restored: a dedup hit
        registrar.unload(neighbour.id)
    finally:
        registrar.stop()

    assert (str(path), True, True, 8) == (
        damaged.value.path,
        "resource r7 is not a pickle" in damaged.value.cause,
        "resource r7 is not a pickle" in again.value.cause,
        neighbour.response,
    )
    with sqlite3.connect(path) as db:  # r7's row is kept as it was
        assert db.execute("SELECT request FROM resources WHERE id = 'r7'").fetchone() == (
            b"\x00\xff\x00",
        )


def test_a_backup_that_failed_to_open_leaves_the_registrar_name_free(tmp_path: Path) -> None:
    make_garbage(tmp_path / "p.db")
    name = unique("P")
    with pytest.raises(rr.CatalogCorruptError):
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, backup_path=tmp_path / "p.db"))

    registrar = rr.ResourceRegistrar.start(name)

    registrar.stop()


@pytest.mark.parametrize(
    ("where", "cause"),
    [
        (lambda tmp: tmp / "missing" / "p.db", "does not exist"),
        (lambda tmp: tmp, "is a directory"),
        (lambda _tmp: Path("/sys/rr_actors_test.db"), "cannot be created"),
    ],
)
def test_an_unusable_backup_path_raises_config_error_naming_it(
    tmp_path: Path, where: Callable[[Path], Path], cause: str
) -> None:
    path = where(tmp_path)
    if path.parent == Path("/sys"):
        try:
            path.touch()
        except OSError:
            pass
        else:
            path.unlink()
            pytest.skip("/sys is writable here")

    with pytest.raises(rr.ConfigError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=unique("P"), backup_path=path))

    assert (True, True) == (str(path) in str(raised.value), cause in str(raised.value))


def test_a_read_only_backup_raises_config_error(tmp_path: Path) -> None:
    if os.geteuid() == 0:
        where = tmp_path / "ro"
        with mounted(where, "1m"):
            write_valid_backup(where / "p.db")
            remount_read_only(where)
            with pytest.raises(rr.ConfigError, match="not readable and writable") as raised:
                SqliteStore.open(where / "p.db")
    else:
        where = tmp_path
        write_valid_backup(where / "p.db")
        (where / "p.db").chmod(0o444)
        with pytest.raises(rr.ConfigError, match="not readable and writable") as raised:
            SqliteStore.open(where / "p.db")

    assert str(where / "p.db") in str(raised.value)


def test_a_backup_in_a_read_only_location_raises_config_error(tmp_path: Path) -> None:
    where = tmp_path / "ro"
    with mounted(where, "1m"):  # (skipped unless root: root ignores directory modes too)
        remount_read_only(where)
        with pytest.raises(rr.ConfigError, match="is not writable") as raised:
            SqliteStore.open(where / "p.db")

    assert str(where / "p.db") in str(raised.value)


def test_quarantine_moves_a_corrupt_backup_aside_so_a_registrar_starts_empty(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    make_garbage(tmp_path / "p.db")
    before = digest(tmp_path / "p.db")

    moved = quarantine_backup(tmp_path / "p.db")
    registrar = start(started, unique("P"), tmp_path / "p.db")

    assert (before, True, False) == (
        digest(moved),
        moved.name.startswith("p.db.corrupt-"),
        registrar.restored,
    )


def test_quarantine_without_a_file_raises_config_error(tmp_path: Path) -> None:
    with pytest.raises(rr.ConfigError, match="no catalog backup"):
        quarantine_backup(tmp_path / "p.db")


# -- restore without decoding, digests, schema 2 ------------------------------------------------


def stored_catalog(path: Path, requests: list[Any]) -> Catalog:
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    for n, request in enumerate(requests):
        catalog.begin_load(f"r{n}", "leaf", request)
        catalog.finish_load(f"r{n}", {"pid": n})
        catalog.add_consumer(f"r{n}", f"q{n}", "C")
    store.write(catalog.drain_changes())
    store.close(erase=False)
    return catalog


def lazily_restored(path: Path) -> tuple[SqliteStore, Catalog, int]:
    """A catalog restored as a registrar restores it, its store, and how many rows wait."""
    store = SqliteStore.open(path)
    restored = store.restore()
    assert restored is not None
    catalog = Catalog.restore(restored.resources, restored.clients, restored.unread)
    return store, catalog, restored.unread.remaining


def test_a_restore_reads_a_served_resource_only_when_a_lookup_needs_it(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", [{"n": n} for n in range(6)])
    store, catalog, waiting = lazily_restored(tmp_path / "p.db")
    try:
        in_memory = len(catalog.resources)
        found = catalog.find("leaf", {"n": 2})  # by digest, through the index
        by_consumer = catalog.resource_of("q4")  # by consumer id, from the columns
        known = (catalog.has_consumer("q5"), catalog.has_consumer("q-never"))
        after = sorted(catalog.resources)
        of_server = [r.id for r in catalog.resources_of("leaf")]
        catalog.check_invariants()
    finally:
        store.close(erase=False)

    assert (6, 0, "r2", "r4", (True, False), ["r2", "r4", "r5"]) == (
        waiting,
        in_memory,
        found.id if found else None,
        by_consumer.id,
        known,
        after,
    )
    assert sorted(of_server) == [f"r{n}" for n in range(6)]


def test_a_consumer_id_holding_the_column_separator_is_restored_all_the_same(
    tmp_path: Path,
) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    for n, query_id in enumerate(["plain", "with\x1funit separator", "with,comma"]):
        catalog.begin_load(f"r{n}", "leaf", n)
        catalog.finish_load(f"r{n}", n)
        catalog.add_consumer(f"r{n}", query_id, "C")
    store.write(catalog.drain_changes())
    store.close(erase=False)

    store, restored, _ = lazily_restored(tmp_path / "p.db")
    try:
        found = [restored.resource_of(q).id for q in ("with,comma", "with\x1funit separator")]
        missing = restored.has_consumer("with")
    finally:
        store.close(erase=False)

    assert (["r2", "r1"], False) == (found, missing)


def test_memory_wins_over_rows_not_written_yet_for_a_lazily_restored_catalog(
    tmp_path: Path,
) -> None:
    """A release or removal not flushed yet (save_interval) must not come back from disk."""
    stored_catalog(tmp_path / "p.db", [{"n": n} for n in range(4)])
    store, catalog, _ = lazily_restored(tmp_path / "p.db")
    try:
        resource = catalog.resource_of("q1")
        catalog.release("q1")
        catalog.begin_unload(resource.id)
        catalog.remove_resource(resource.id)
        pending = catalog.drain_changes()  # held back, as a save_interval registrar does
        seen = (
            catalog.has_consumer("q1"),
            catalog.find("leaf", {"n": 1}),
            "r1" in catalog.read_all(),
        )
        store.write(pending)
    finally:
        store.close(erase=False)

    assert ((False, None, False), ["r0", "r2", "r3"]) == (
        seen,
        sorted(r.id for r in read_backup(tmp_path / "p.db").resources),
    )


def test_consumers_from_an_origin_include_those_of_resources_still_on_disk(
    tmp_path: Path,
) -> None:
    store = SqliteStore.open(tmp_path / "p.db")
    store.load()
    catalog = Catalog()
    for n in range(6):
        catalog.begin_load(f"r{n}", "leaf", n)
        catalog.finish_load(f"r{n}", n)
        catalog.add_consumer(f"r{n}", f"a{n}", "A")
        if n % 2:
            catalog.add_consumer(f"r{n}", f"b{n}", "B")
    store.write(catalog.drain_changes())
    store.close(erase=False)

    store, restored, _ = lazily_restored(tmp_path / "p.db")
    try:
        from_b = restored.consumers_from("B")
        listed = [r.id for r in restored.read_all().values()]
    finally:
        store.close(erase=False)

    assert (["b1", "b3", "b5"], [f"r{n}" for n in range(6)]) == (sorted(from_b), listed)


def test_a_restore_leaves_requests_and_responses_encoded_until_first_used(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", [{"n": n} for n in range(5)])
    store = SqliteStore.open(tmp_path / "p.db")
    rows = store.load()
    store.close(erase=False)
    assert rows is not None

    catalog = Catalog.restore(*rows)
    found = catalog.find("leaf", {"n": 3})

    assert found is not None
    decoded = [sorted({"request", "response"} & set(vars(r))) for r in catalog.resources.values()]
    assert [[], [], [], ["request"], []] == decoded
    assert ({"n": 3}, {"pid": 3}) == (found.request, found.response)


def catalog_with_a_gone_class(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Store resources r0 ("plain") and r1 ("other"); r1's response is of a class gone since."""
    module = type(os)("rr_gone_module")
    exec("class Thing:\n    pass\n", module.__dict__)  # noqa: S102 - a throwaway module
    monkeypatch.setitem(sys.modules, "rr_gone_module", module)
    stored_catalog(path, ["plain", "other"])
    db = sqlite3.connect(path)
    db.execute("UPDATE resources SET response = ? WHERE id = 'r1'", (pickle.dumps(module.Thing()),))
    db.commit()
    db.close()
    monkeypatch.delitem(sys.modules, "rr_gone_module")


def test_a_stored_value_whose_class_is_gone_raises_catalog_corrupt_error_when_first_used(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    catalog_with_a_gone_class(tmp_path / "p.db", monkeypatch)

    catalog = reopen(tmp_path / "p.db")
    with pytest.raises(rr.CatalogCorruptError) as raised:
        _ = catalog.resources["r1"].response

    assert (str(tmp_path / "p.db"), True, {"pid": 0}) == (
        raised.value.path,
        "response of resource r1 cannot be read" in raised.value.cause,
        catalog.resources["r0"].response,
    )


def test_a_new_response_for_a_restored_resource_reaches_the_file(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", ["a", "b"])
    store = SqliteStore.open(tmp_path / "p.db")
    rows = store.load()
    assert rows is not None
    catalog = Catalog.restore(*rows)
    _ = catalog.resources["r0"].response  # decoded: not a change
    catalog.set_response("r0", "old one decoded, then kept")
    catalog.set_response("r1", "replaced without a look")
    catalog.set_response("r0", catalog.resources["r0"].response)
    store.write(catalog.drain_changes())
    store.close(erase=False)

    assert ["old one decoded, then kept", "replaced without a look"] == [
        r.response for r in reopen(tmp_path / "p.db").resources.values()
    ]


def test_the_stored_digest_is_the_same_in_a_process_with_another_string_hash_seed(
    tmp_path: Path,
) -> None:
    request = {
        "cmd": ["driver", "--id", "7"],
        "on": True,
        "rate": 2.5,
        "mode": ResourceState.LOADED,
    }
    stored_catalog(tmp_path / "p.db", [request])
    code = (
        "from rr_actors._catalog import ResourceState, request_digest; "
        "print(request_digest({'rate': 2.5, 'on': 1, 'cmd': ['driver', '--id', '7'], "
        "'mode': ResourceState.LOADED}))"
    )
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout
    db = sqlite3.connect(tmp_path / "p.db")
    try:
        [(stored,)] = db.execute("SELECT digest FROM resources").fetchall()
    finally:
        db.close()

    assert int(out) == stored


def test_digests_written_under_another_scheme_are_recomputed_when_the_file_is_opened(
    tmp_path: Path,
) -> None:
    stored_catalog(tmp_path / "p.db", [{"n": 1}, ["x"]])
    db = sqlite3.connect(tmp_path / "p.db")
    db.execute("UPDATE resources SET digest = 42")
    db.execute("UPDATE rr_actors_schema SET digest_scheme = 'another-python'")
    db.commit()
    db.close()

    catalog = reopen(tmp_path / "p.db")

    assert ("r0", "r1") == (catalog.find("leaf", {"n": 1.0}).id, catalog.find("leaf", ["x"]).id)


def write_v1_backup(path: Path) -> None:
    """A backup as rr_actors wrote it with schema version 1."""
    db = sqlite3.connect(path, isolation_level=None)
    db.execute(f"PRAGMA application_id = {schema.APPLICATION_ID}")
    schema.MIGRATIONS[0](db)
    db.execute("UPDATE rr_actors_schema SET version = 1")
    db.execute("PRAGMA journal_mode = WAL")
    rows = [(1, "r0", "leaf", "loaded", {"n": 0}, "zero"), (2, "r1", "leaf", "loading", "x", None)]
    for seq, rid, server, state, request, response in rows:
        db.execute(
            "INSERT INTO resources VALUES (?, ?, ?, ?, ?, ?)",
            (seq, rid, server, state, codec.dumps(request), codec.dumps(response)),
        )
    db.execute("INSERT INTO consumers VALUES (3, 'q0', 'r0', 'C')")
    db.execute(
        "INSERT INTO clients VALUES (4, 'd0', 'leaf', 'P', 'me', ?, NULL, 'r0', 1)",
        (codec.dumps(5),),
    )
    db.close()


def test_a_version_1_backup_is_migrated_to_digests_integer_states_and_consumer_rows(
    tmp_path: Path,
) -> None:
    write_v1_backup(tmp_path / "p.db")

    catalog = reopen(tmp_path / "p.db")

    db = sqlite3.connect(tmp_path / "p.db")
    try:
        stored = db.execute("SELECT version, digest_scheme FROM rr_actors_schema").fetchall()
        digests = db.execute("SELECT digest, state FROM resources ORDER BY seq").fetchall()
        consumers = db.execute("SELECT query_id, resource FROM consumers").fetchall()
    finally:
        db.close()
    assert [(schema.SCHEMA_VERSION, DIGEST_SCHEME)] == stored
    assert [(request_digest({"n": 0}), 1), (request_digest("x"), 0)] == digests
    assert [("q0", 1)] == consumers
    assert (
        "r0",
        ["q0"],
        ResourceState.LOADING,
        ["d0"],
    ) == (
        catalog.find("leaf", {"n": 0}).id,
        list(catalog.resources["r0"].consumers),
        catalog.resources["r1"].state,
        [c.query.id for c in catalog.dependencies("r0")],
    )


def test_a_request_without_a_digest_is_restored_and_found_by_equality(tmp_path: Path) -> None:
    stored_catalog(tmp_path / "p.db", [ResourceState.LOADED, ("tuple", ResourceState.LOADING)])

    catalog = reopen(tmp_path / "p.db")

    assert ("r0", "r1") == (
        catalog.find("leaf", ResourceState.LOADED).id,
        catalog.find("leaf", ("tuple", ResourceState.LOADING)).id,
    )


def test_a_call_that_meets_an_unreadable_restored_value_fails_and_the_registrar_keeps_serving(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    catalog_with_a_gone_class(tmp_path / "p.db", monkeypatch)
    name = f"p-{uuid.uuid4().hex[:8]}"
    provider = rr.ResourceRegistrar.start(rr.RegistrarConfig(name, backup_path=tmp_path / "p.db"))
    consumer = rr.ResourceRegistrar.start(f"c-{uuid.uuid4().hex[:8]}")
    try:
        provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
        with pytest.raises(rr.CatalogCorruptError):
            consumer.call(name, "leaf", "other", timeout=5)
        served = consumer.call(name, "leaf", "plain", timeout=5)

        assert ({"pid": 0}, True) == (served.response, provider.is_alive())
    finally:
        consumer.stop()
        provider.stop()


# -- every response the catalog sets is written -----------------------------------------------


def written_once(path: Path) -> Catalog:
    """A backup holding resource r1 (consumer q1, response {"status": "starting"}) and client d1."""
    store = SqliteStore.open(path)
    store.load()
    catalog = Catalog()
    catalog.begin_load("r1", "leaf", {"k": 1})
    catalog.add_consumer("r1", "q1", "C")
    catalog.finish_load("r1", {"status": "starting"})
    catalog.add_client(ClientRecord(make_query("d1", 1), "r1"))
    catalog.client_loaded("d1", {"status": "starting"})
    store.write(catalog.drain_changes())
    store.close(erase=False)
    return catalog


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

    def start_provider() -> rr.ResourceRegistrar:
        provider = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=name, backup_path=path, save_on_modify=True)
        )
        provider.register_server("leaf", load=lambda r: {"pid": 42}, unload=noop_unload)
        return provider

    provider = start_provider()
    consumer = rr.ResourceRegistrar.start(unique("C"))
    try:
        query = consumer.call(name, "leaf", {"cmd": "x"}, timeout=5)
        provider.stop()
        provider = start_provider()
        provider.update_response(query.id, None)
        provider.stop()
    finally:
        consumer.stop()
        provider.stop()

    assert [None] == [r.response for r in read_backup(path).resources]


# -- rows that cannot be right ----------------------------------------------------------------


def duplicate_resource(db: sqlite3.Connection) -> None:
    db.execute("DROP INDEX resources_by_id")  # the unique index refuses a second row
    db.execute(
        "INSERT INTO resources (seq, id, server, state, digest, request, response) "
        "SELECT 100, id, server, state, digest, request, response FROM resources WHERE id = 'r1'"
    )


def duplicate_consumer(db: sqlite3.Connection) -> None:
    db.execute(
        "INSERT INTO consumers (seq, query_id, resource, origin_rr) "
        "SELECT 101, query_id, resource, origin_rr FROM consumers"
    )


def duplicate_client(db: sqlite3.Connection) -> None:
    db.execute(
        "INSERT INTO clients SELECT 102, query_id, server, serving_rr, origin_rr, request, "
        "response, parent, loaded, request_text FROM clients"
    )


def state_minus_one(db: sqlite3.Connection) -> None:
    db.execute("UPDATE resources SET state = -1")


def state_three(db: sqlite3.Connection) -> None:
    db.execute("UPDATE resources SET state = 3")


def state_text(db: sqlite3.Connection) -> None:
    db.execute("UPDATE resources SET state = 'loaded'")


@pytest.mark.parametrize(
    ("damage", "cause"),
    [
        (duplicate_resource, "index resources_by_id is missing"),
        (duplicate_consumer, "consumer query id q1 is stored twice"),
        (duplicate_client, "client query id d1 is stored twice"),
        (state_minus_one, "unknown state -1"),
        (state_three, "unknown state 3"),
        (state_text, "unknown state 'loaded'"),
    ],
)
def test_a_duplicate_id_or_unknown_state_in_a_backup_raises_catalog_corrupt_error(
    tmp_path: Path, damage: Callable[[sqlite3.Connection], None], cause: str
) -> None:
    path = tmp_path / "p.db"
    written_once(path)
    db = sqlite3.connect(path)
    damage(db)
    db.commit()
    db.close()

    with pytest.raises(rr.CatalogCorruptError) as restored:  # as a registrar restores
        SqliteStore.open(path).restore()
    with pytest.raises(rr.CatalogCorruptError) as loaded:
        SqliteStore.open(path).load()
    with pytest.raises(rr.CatalogCorruptError) as inspected:
        read_backup(path)

    assert [(str(path), True)] * 3 == [
        (e.value.path, cause in e.value.cause) for e in (restored, loaded, inspected)
    ]


# -- failures while writing -------------------------------------------------------------------


class CommitFails:
    """A connection whose COMMIT fails after SQLite has ended the transaction (I/O error)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self.db = db

    @property
    def in_transaction(self) -> bool:
        return self.db.in_transaction

    def execute(self, sql: str, *args: Any) -> Any:
        if sql == "COMMIT":
            self.db.execute("ROLLBACK")
            raise sqlite3.OperationalError("disk I/O error (simulated)")
        return self.db.execute(sql, *args)

    def executemany(self, sql: str, *args: Any) -> Any:
        return self.db.executemany(sql, *args)

    def close(self) -> None:
        self.db.close()


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


class InsertFailsOnce:
    """A connection whose first INSERT fails (an I/O error in a one-statement write)."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self.db = db
        self.failed = False

    @property
    def in_transaction(self) -> bool:
        return self.db.in_transaction

    def execute(self, sql: str, *args: Any) -> Any:
        if sql.startswith("INSERT") and not self.failed:
            self.failed = True
            raise sqlite3.OperationalError("disk I/O error (simulated)")
        return self.db.execute(sql, *args)

    def close(self) -> None:
        self.db.close()


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


class FlakyStore:
    """A `CatalogStore` whose first `fail` writes raise; it records what it was given."""

    path = "flaky"

    def __init__(self, fail: int) -> None:
        self.fail = fail
        self.written: list[tuple[list[str], list[str]]] = []
        self.closed = False

    def load(self) -> None:
        return None

    def write(self, changes: Changes) -> None:
        if self.fail:
            self.fail -= 1
            raise rr.CatalogWriteError(self.path, "ENOSPC (simulated)", errno.ENOSPC)
        self.written.append((list(changes.resources), list(changes.clients)))

    def close(self, *, erase: bool) -> None:
        self.closed = True


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
