"""What a restart must give back, clause by clause (rules 11, 15 and 16).

Each test here covers a clause that a mutation audit found unguarded: breaking it failed
no other test.

- Rule 15: a backup that cannot be read raises `CatalogCorruptError` naming the file in
  its message (not only in its `path` attribute).
- Rules 12 and 16, the consumer's side: a consumer registrar killed after its provider
  answered a call, but before it committed the answer, leaves a pending client record in
  its backup while the provider holds the consumer id. The death watch does not release
  a consumer that will be restarted, so the restarted registrar must give that id back;
  otherwise the resource leaks at the provider for good.
- Rule 11: `set_status_callback` re-attaches a callback to a query restored after a
  restart, and statuses reach it.
- Rules 4 and 16 (from a review): a sub-call that a failed load's thread sends after the
  failure has no owner; a durable agent that crashes before its answer gives it back
  after the restart, and so does a restart that finds a dependency whose resource is
  gone.
"""

from __future__ import annotations

import contextlib
import contextvars
import sqlite3
import threading
import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._catalog import Changes, ClientRecord
from rr_actors._store.files import read_backup
from rr_actors._store.sqlite import SqliteStore
from rr_actors.testing import catalog_snapshot, crash, expect_restart
from tests.support.gating import GatedLoad


def _name(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


def test_catalog_corrupt_error_names_the_file_in_its_message(tmp_path: Path) -> None:
    path = tmp_path / "garbage.db"
    path.write_bytes(b"this is not an SQLite database, not at all" * 100)

    with pytest.raises(rr.CatalogCorruptError) as raised:
        rr.ResourceRegistrar.start(rr.RegistrarConfig(name=_name("P"), backup_path=path))

    assert str(path) in str(raised.value)


def test_a_restarted_consumer_gives_back_an_id_its_provider_answered_but_it_never_committed(
    tmp_path: Path,
) -> None:
    path = tmp_path / "consumer.db"
    unloads: list[Any] = []
    unloaded = threading.Event()

    def unload(request: Any, _response: Any) -> None:
        unloads.append(request)
        unloaded.set()

    provider = rr.ResourceRegistrar.start(_name("P"))
    consumer_config = rr.RegistrarConfig(name=_name("C"), backup_path=path, save_on_modify=True)
    consumer = rr.ResourceRegistrar.start(consumer_config)
    restarted: rr.ResourceRegistrar | None = None
    with expect_restart(consumer.name):  # as a supervisor does: no death watch
        try:
            provider.register_server("leaf", load=lambda r: {"pid": r}, unload=unload)
            query = consumer.call(provider.name, "leaf", "camera", timeout=5)
            crash(consumer)
            assert [query.id] == [q.id for q in provider.server_queries("leaf")]  # kept: restart
            # The kill came after the provider answered and before the consumer committed the
            # answer: its backup holds the record as written before the load went out.
            store = SqliteStore.open(path)
            try:
                pending = ClientRecord(query.with_response(None), None, loaded=False)
                store.write(Changes({}, {query.id: pending}))
            finally:
                store.close(erase=False)
            assert [False] == [c.loaded for c in read_backup(path).clients]

            restarted = rr.ResourceRegistrar.start(consumer_config)

            assert unloaded.wait(5), "the provider still holds the id of the lost call"
            assert (["camera"], [], []) == (
                unloads,
                provider.server_queries("leaf"),
                restarted.client_queries(),
            )
        finally:
            if restarted is not None:
                restarted.stop()
            provider.stop()


def test_set_status_callback_reattaches_a_callback_to_a_query_restored_after_a_restart(
    tmp_path: Path,
) -> None:
    """Rule 11: after a restart the consumer re-attaches its callback; status reaches it."""
    path = tmp_path / "consumer.db"
    updates: list[Any] = []
    got = threading.Event()

    def on_status(query: rr.Query, update: rr.StatusUpdate) -> None:
        updates.append((query.id, update.query_id, update.status))
        got.set()

    provider = rr.ResourceRegistrar.start(_name("P"))
    consumer_config = rr.RegistrarConfig(name=_name("C"), backup_path=path, save_on_modify=True)
    consumer = rr.ResourceRegistrar.start(consumer_config)
    restarted: rr.ResourceRegistrar | None = None
    with expect_restart(consumer.name):
        try:
            provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: None)
            query = consumer.call(provider.name, "leaf", "camera", timeout=5)
            crash(consumer)
            restarted = rr.ResourceRegistrar.start(consumer_config)

            restarted.set_status_callback(query.id, on_status)
            provider.send_status(query.id, rr.Status.ERROR, "lost", timeout=5)

            assert got.wait(5)
            assert [(query.id, query.id, rr.Status.ERROR)] == updates
        finally:
            if restarted is not None:
                restarted.stop()
            provider.stop()


class SensorError(Exception):
    """An application exception that knows nothing of rr_actors."""


def test_a_sub_call_written_down_after_its_load_failed_is_given_back_after_a_crash(
    tmp_path: Path,
) -> None:
    # A durable agent writes a call down before sending it. A sub-call that goes out
    # after its load failed has no owner any more: a crash before its answer must still
    # leave the restarted agent able to give the id back (rules 4 and 16).
    config = rr.RegistrarConfig(name=_name("A"), backup_path=tmp_path / "a.db", save_on_modify=True)
    provider = rr.ResourceRegistrar.start(_name("P"))
    agent = rr.ResourceRegistrar.start(config)
    consumer = rr.ResourceRegistrar.start(_name("C"))
    restarted: rr.ResourceRegistrar | None = None
    with expect_restart(config.name):  # as a supervisor does: no death watch
        failed, started, gate, unloaded = (threading.Event() for _ in range(4))
        pool = ThreadPoolExecutor(1)
        try:
            leaf = GatedLoad(gate, started)
            provider.register_server("leaf", load=leaf, unload=lambda r, s: unloaded.set())

            def sub_call(request: Any) -> rr.Query:
                assert failed.wait(10)
                return agent.call(provider.name, "leaf", request, timeout=10)

            def composite(request: Any) -> Any:
                pool.submit(contextvars.copy_context().run, sub_call, request)
                raise SensorError("failed before its sub-call went out")

            agent.register_server("composite", load=composite, unload=lambda r, s: None)
            with pytest.raises(rr.ResourceLoadError):
                consumer.call(agent.name, "composite", "x")
            failed.set()
            assert started.wait(10)  # the sub-call is at the provider: written down before
            agent.client_queries()  # the agent handled (and committed) what came before
            crash(agent)

            restarted = rr.ResourceRegistrar.start(config)
            gate.set()

            assert unloaded.wait(10), "the provider still holds the sub-call's id"
            assert [] == provider.server_queries("leaf")
            assert ((), ()) == (
                catalog_snapshot(restarted).resources,
                catalog_snapshot(restarted).clients,
            )
        finally:
            gate.set()
            failed.set()
            pool.shutdown()
            for registrar in (consumer, restarted, provider):
                if registrar is not None:
                    registrar.stop()


def test_a_restart_gives_back_a_dependency_whose_resource_is_gone(tmp_path: Path) -> None:
    # A backup may hold a dependency whose resource is not there (written by an older
    # version, which recorded a sub-call that outlived its failed load): nothing else
    # would ever release it, so the restart gives it back at its provider.
    path = tmp_path / "a.db"
    config = rr.RegistrarConfig(name=_name("A"), backup_path=path, save_on_modify=True)
    provider = rr.ResourceRegistrar.start(_name("P"))
    agent = rr.ResourceRegistrar.start(config)
    restarted: rr.ResourceRegistrar | None = None
    with expect_restart(config.name):
        unloaded = threading.Event()
        try:
            provider.register_server("leaf", load=lambda r: r, unload=lambda r, s: unloaded.set())
            query = agent.call(provider.name, "leaf", "camera", timeout=5)
            crash(agent)
            with contextlib.closing(sqlite3.connect(tmp_path / "a.db")) as db, db:
                db.execute(
                    "UPDATE clients SET parent = 'a-resource-that-is-gone' WHERE query_id = ?",
                    (query.id,),
                )
            assert ["a-resource-that-is-gone"] == [c.parent for c in read_backup(path).clients]

            restarted = rr.ResourceRegistrar.start(config)

            assert unloaded.wait(5), "the provider still holds the orphaned dependency"
            assert [] == provider.server_queries("leaf")
            assert () == catalog_snapshot(restarted).clients
        finally:
            for registrar in (restarted, provider):
                if registrar is not None:
                    registrar.stop()
