"""What the store tests share: the child processes' functions (sent by reference), the
stores and backups they start from, recording callbacks and a save-interval clock."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hashlib
import os
import pickle
import random
import sqlite3
import sys
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import (
    Catalog,
    Changes,
    ClientRecord,
    ResourceState,
)
from rr_actors._store import schema
from rr_actors._store.restore import read_backup
from rr_actors._store.saver import SqliteStore
from rr_actors.testing import catalog_snapshot
from tests.support.durable_pair import (
    new_store,
    noop_unload,
    start_consumer,
    start_pair,
    start_provider,
)


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


def child_gave_up_not_unloaded(names: tuple[str, str], paths: tuple[str, str], conn: Any) -> None:
    """C's only call of a P leaf gives up while its load runs; the load ends, written
    loaded with no consumer, and P is held before the leaf's unload began (the
    `unload_resource` point), then killed there. (A last release is written with its
    unload mark: only a load whose every caller gave up leaves a resource nobody holds.)"""
    from rr_actors.testing import intercept  # noqa: PLC0415

    p_name, c_name = names
    started, ends = threading.Event(), threading.Event()

    def load(request: Any) -> Any:
        started.set()
        ends.wait(60)
        return {"leaf": request}

    provider = start_provider(p_name, paths[0], load=load)
    consumer = start_consumer(c_name, paths[1])

    def held_there(_resource: Any) -> None:
        conn.send("held")  # (the actor is held here: no snapshot)
        threading.Event().wait(60)  # the parent kills this process here

    intercept(provider, "unload_resource", before=held_there)

    async def give_up_once_it_runs() -> None:
        call = asyncio.ensure_future(consumer.acall(p_name, "leaf", {"released": 1}))
        assert await asyncio.to_thread(started.wait, 30)  # (one never run is never loaded)
        call.cancel()  # withdrawn: its Abandon is sent before the cancellation ends
        with contextlib.suppress(asyncio.CancelledError):
            await call

    asyncio.run(give_up_once_it_runs())
    ends.set()  # (its load ends after the Abandon: a consumer nobody holds)
    conn.recv()  # never answered


RunAndKill = Callable[..., list[Any]]


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


def consumer_ids(path: Path) -> set[str]:
    """Consumer ids stored in a backup, read through a separate connection."""
    return {q for r in read_backup(path).resources for q in r.consumers}


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
    finally:
        store.close(erase=False)  # (one store a file at a time: `files.claim`)
    lazily = reopen_lazily(path)
    assert shape_of(catalog) == shape_of(lazily)
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
        [(c.query, c.parent, c.loaded) for c in catalog.client_records()],
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
        elif choice in (6, 7) and catalog.client_records():
            qid = rng.choice([c.query.id for c in catalog.client_records()])
            if choice == 6:
                catalog.client_loaded(qid, rng.randrange(9))
            else:
                catalog.remove_client(qid)
        yield


def write_valid_backup(path: Path) -> None:
    store, catalog = new_store(path)
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


def stored_catalog(path: Path, requests: list[Any]) -> Catalog:
    store, catalog = new_store(path)
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
            (seq, rid, server, state, schema.dumps(request), schema.dumps(response)),
        )
    db.execute("INSERT INTO consumers VALUES (3, 'q0', 'r0', 'C')")
    db.execute(
        "INSERT INTO clients VALUES (4, 'd0', 'leaf', 'P', 'me', ?, NULL, 'r0', 1)",
        (schema.dumps(5),),
    )
    db.close()


def written_once(path: Path) -> Catalog:
    """A backup holding resource r1 (consumer q1, response {"status": "starting"}) and client d1."""
    store, catalog = new_store(path)
    catalog.begin_load("r1", "leaf", {"k": 1})
    catalog.add_consumer("r1", "q1", "C")
    catalog.finish_load("r1", {"status": "starting"})
    catalog.add_client(ClientRecord(make_query("d1", 1), "r1"))
    catalog.client_loaded("d1", {"status": "starting"})
    store.write(catalog.drain_changes())
    store.close(erase=False)
    return catalog


def duplicate_resource(db: sqlite3.Connection) -> None:
    db.execute("DROP INDEX resources_by_id")  # the unique index refuses a second row
    db.execute(
        "INSERT INTO resources (seq, id, server, state, digest, request, response) "
        "SELECT 100, id, server, state, digest, request, response FROM resources WHERE id = 'r1'"
    )


def duplicate_consumer(db: sqlite3.Connection) -> None:
    db.execute("DROP INDEX consumers_by_query")  # the unique index refuses a second row
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


class FlakyStore:
    """A `CatalogStore` whose first `fail` writes raise; it records what it was given."""

    path = "flaky"
    damaged = None  # (its file is never damaged)

    def __init__(self, fail: int) -> None:
        self.fail = fail
        self.written: list[tuple[list[str], list[str]]] = []
        self.closed = False

    def load(self) -> None:
        return None

    def write(self, changes: Changes, told: Sequence[rr.events.Event] = ()) -> None:
        if self.fail:
            self.fail -= 1
            raise rr.CatalogWriteError(self.path, "ENOSPC (simulated)", errno.ENOSPC)
        self.written.append((list(changes.resources), list(changes.clients)))

    def close(self, *, erase: bool) -> None:
        self.closed = True


def write_unloading(path: Path) -> None:
    """A backup whose resource r-stop was being unloaded when the process died."""
    store, catalog = new_store(path)
    catalog.begin_load("r-stop", "start_process", {"cmd": "sleep"})
    catalog.finish_load("r-stop", {"pid": 42})
    catalog.begin_unload("r-stop")
    store.write(catalog.drain_changes())
    store.close(erase=False)
