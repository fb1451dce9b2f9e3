"""Provider and consumers reconcile their catalogs after a restart (issue 16).

Real manager processes on a system, real SIGKILL, real backups: a provider killed while
a consumer releases an id there, restarted on its backup; backups that lost a commit
(the row removed by hand, as a truncated WAL or a non-durable save would lose it).

- Ids a consumer no longer holds (it released them while the provider was down, or its
  own restart lost them) are released at the provider.
- Ids the provider no longer knows are reported to the consumer as `FATAL` (its status
  callback) and forgotten there.
"""

from __future__ import annotations

import contextlib
import sqlite3
import sys
import threading
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors.testing import (
    RemoteRegistrar,
    SharedObjects,
    crash,
    expect_restart,
    intercept,
    run_on_actor,
)
from tests.support.durable_pair import durable_config
from tests.support.gating import GatedLoad

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def provider_setup(unloads: Any, unloaded: Any = None) -> Callable[[rr.ResourceRegistrar], None]:
    """A provider with a server "leaf" whose unloads are recorded in `unloads`.

    `unloaded` (a shared event) is set after each unload was recorded.
    """

    def setup(registrar: rr.ResourceRegistrar) -> None:
        def unload(request: Any, _response: Any) -> None:
            unloads.append(request)
            if unloaded is not None:
                unloaded.set()

        registrar.register_server("leaf", load=lambda r: {"for": r}, unload=unload)

    return setup


def composite_setup(provider: str) -> Callable[[rr.ResourceRegistrar], None]:
    """A consumer with a server "composite" whose load calls `provider`/leaf (a dependency)."""

    def setup(registrar: rr.ResourceRegistrar) -> None:
        def load(request: Any) -> Any:
            return registrar.call(provider, "leaf", request, timeout=10).response

        registrar.register_server("composite", load=load, unload=lambda _r, _s: None)

    return setup


def delete_rows(backup: Path, table: str, query_id: str) -> None:
    """Remove a row from a dead registrar's backup, as a lost commit would leave it."""
    with contextlib.closing(sqlite3.connect(backup)) as db, db:
        deleted = db.execute(f"DELETE FROM {table} WHERE query_id = ?", (query_id,))  # noqa: S608
        assert 1 == deleted.rowcount


def test_an_id_released_while_its_provider_was_down_is_released_after_its_restart(
    managers: Callable[..., RemoteRegistrar], tmp_path: Path, process_helpers: SharedObjects
) -> None:
    unloads, unloaded = process_helpers.list(), process_helpers.event()
    config = durable_config("provider", tmp_path)
    provider = managers(config, provider_setup(unloads, unloaded))
    consumer = managers(durable_config("consumer", tmp_path), composite_setup(config.name))
    top = consumer.call(consumer.name, "composite", "camera", timeout=10)
    assert 1 == len(provider.server_queries("leaf"))  # the composite's dependency

    with expect_restart(config.name):  # as its supervisor would: no death watch
        provider.kill()
    consumer.unload(top.id, timeout=10)  # releases the dependency: the provider is down
    assert [] == consumer.client_queries()
    restarted = managers(config, provider_setup(unloads, unloaded))

    assert unloaded.wait(10)
    assert (["camera"], []) == (unloads, restarted.server_queries("leaf"))


def test_an_id_the_restarted_provider_lost_is_reported_fatal_and_forgotten(
    managers: Callable[..., RemoteRegistrar],
    tmp_path: Path,
    process_helpers: SharedObjects,
    eventually: Callable[..., bool],
) -> None:
    unloads, heard = process_helpers.list(), process_helpers.list()
    config = durable_config("provider", tmp_path)
    provider = managers(config, provider_setup(unloads))
    consumer = managers(durable_config("consumer", tmp_path), None)

    def note(query: rr.Query, update: rr.StatusUpdate) -> None:
        heard.append((query.id, update.status))

    kept = consumer.call(config.name, "leaf", "camera", on_status=note, timeout=10)
    lost = consumer.call(config.name, "leaf", "camera", on_status=note, timeout=10)
    with expect_restart(config.name):  # as its supervisor would: no death watch
        provider.kill()
    delete_rows(Path(config.backup_path), "consumers", lost.id)  # type: ignore[arg-type]
    restarted = managers(config, provider_setup(unloads))

    assert eventually(lambda: len(heard) > 0, timeout=10)  # its callback runs on a worker
    assert [(lost.id, rr.Status.FATAL)] == heard
    assert [kept.id] == [q.id for q in consumer.client_queries()]
    assert [kept.id] == [q.id for q in restarted.server_queries("leaf")]
    assert [] == unloads


def test_an_id_a_restarted_consumer_lost_is_released_at_its_provider(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    unloads: list[Any] = []
    unloaded = threading.Event()

    def unload(request: Any, _response: Any) -> None:
        unloads.append(request)
        unloaded.set()

    provider = rr.ResourceRegistrar.start(f"provider-{uuid.uuid4().hex[:8]}")
    started.append(provider)
    provider.register_server("leaf", load=lambda r: r, unload=unload)
    config = durable_config("consumer", tmp_path)
    consumer = rr.ResourceRegistrar.start(config)
    kept = consumer.call(provider.name, "leaf", "camera", timeout=10)
    lost = consumer.call(provider.name, "leaf", "lidar", timeout=10)
    with expect_restart(config.name):  # as its supervisor would: no death watch
        crash(consumer)
    delete_rows(Path(config.backup_path), "clients", lost.id)  # type: ignore[arg-type]

    restarted = rr.ResourceRegistrar.start(config)
    started.append(restarted)

    assert unloaded.wait(10)
    assert (["lidar"], [kept.id]) == (unloads, [q.id for q in provider.server_queries("leaf")])
    assert [kept.id] == [q.id for q in restarted.client_queries()]


def test_a_retry_after_the_provider_reconciled_finds_the_id_it_committed_before_it_died(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    # Rule 17, case 3: the provider committed the consumer id and died before its answer
    # left; the call failed with RegistrarUnavailableError. The restarted provider
    # reconciles with the consumer before the retry comes: the id must stay held there.
    load = GatedLoad(threading.Event(), threading.Event(), lambda request: {"for": request})
    loads, gate, entered = load.requests, load.gate, load.started

    def serve(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("leaf", load=load, unload=lambda _r, _s: None)

    config = durable_config("provider", tmp_path)
    provider = rr.ResourceRegistrar.start(config, setup=serve)
    consumer = rr.ResourceRegistrar.start(f"consumer-{uuid.uuid4().hex[:8]}")
    started.append(consumer)
    qid = str(uuid.uuid4())
    with ThreadPoolExecutor(1) as pool:
        call = pool.submit(consumer.call, config.name, "leaf", "camera", query_id=qid, timeout=10)
        assert entered.wait(10)
        with expect_restart(config.name):  # as its supervisor would: no death watch
            crash(provider)
        with pytest.raises(rr.RegistrarUnavailableError):
            call.result(timeout=10)
    gate.set()
    commit_as_answered(Path(config.backup_path), qid, consumer.name)  # type: ignore[arg-type]
    reconciled = threading.Event()

    def setup(registrar: rr.ResourceRegistrar) -> None:
        serve(registrar)
        intercept(registrar, "reconcile", after=lambda _message: reconciled.set())

    restarted = rr.ResourceRegistrar.start(config, setup=setup)
    started.append(restarted)
    assert reconciled.wait(10)

    retry = consumer.call(config.name, "leaf", "camera", query_id=qid, timeout=10)

    assert ({"for": "camera"}, ["camera"]) == (retry.response, loads)
    assert [qid] == [q.id for q in restarted.server_queries("leaf")]


def test_a_failed_call_the_provider_kept_at_reconciling_is_given_back_when_its_consumer_stops(
    tmp_path: Path, started: list[rr.ResourceRegistrar]
) -> None:
    # Rule 17 case 3, then rule 12: the provider committed the consumer id and died before
    # its answer left. The restarted provider reconciles; the consumer lists the failed
    # call (a retry may come), so the provider keeps the id. No retry comes, and the
    # consumer stops: its stop gives the id back. (A kill-heavy experiment's check found
    # a stopped consumer's id held at its provider to the end: the `end` rule.)
    load = GatedLoad(threading.Event(), threading.Event(), lambda request: {"for": request})
    gate, entered = load.gate, load.started
    unloaded = threading.Event()

    def serve(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server("leaf", load=load, unload=lambda _r, _s: unloaded.set())

    config = durable_config("provider", tmp_path)
    provider = rr.ResourceRegistrar.start(config, setup=serve)
    consumer = rr.ResourceRegistrar.start(f"consumer-{uuid.uuid4().hex[:8]}")
    started.append(consumer)
    qid = str(uuid.uuid4())
    with ThreadPoolExecutor(1) as pool:
        call = pool.submit(consumer.call, config.name, "leaf", "camera", query_id=qid, timeout=10)
        assert entered.wait(10)
        with expect_restart(config.name):  # as its supervisor would: no death watch
            crash(provider)
        with pytest.raises(rr.RegistrarUnavailableError):
            call.result(timeout=10)
    gate.set()
    commit_as_answered(Path(config.backup_path), qid, consumer.name)  # type: ignore[arg-type]
    reconciled = threading.Event()

    def setup(registrar: rr.ResourceRegistrar) -> None:
        serve(registrar)
        intercept(registrar, "reconcile", after=lambda _message: reconciled.set())

    restarted = rr.ResourceRegistrar.start(config, setup=setup)
    started.append(restarted)
    assert reconciled.wait(10)
    run_on_actor(consumer, lambda: None).get(timeout=10)  # it handled the answer (told first)
    assert [qid] == [q.id for q in restarted.server_queries("leaf")]  # kept for a retry

    consumer.stop()

    assert unloaded.wait(10)
    assert [] == restarted.server_queries("leaf")


def commit_as_answered(backup: Path, query_id: str, origin: str) -> None:
    """Write the commit the provider's crash cut short: its one resource, loaded, held by
    `query_id` (what a provider killed after its commit, before its answer, leaves)."""
    with contextlib.closing(sqlite3.connect(backup)) as db, db:
        (seq,) = db.execute("SELECT seq FROM resources").fetchone()
        (last,) = db.execute(
            "SELECT max(seq) FROM (SELECT seq FROM resources UNION SELECT seq FROM consumers)"
        ).fetchone()
        db.execute(
            "UPDATE resources SET state = 1, response = ? WHERE seq = ?",
            (cloudpickle.dumps({"for": "camera"}), seq),
        )
        db.execute(
            "INSERT INTO consumers (resource, seq, query_id, origin_rr) VALUES (?, ?, ?, ?)",
            (seq, last + 1, query_id, origin),
        )
