"""A durable registrar whose backup cannot be written (a real full tmpfs): callers hear at once.

With `save_on_modify` a load or unload is durable before its caller gets the answer
(rule 14). When the disk is full the caller fails at once with a `CatalogWriteError`
naming the file and `ENOSPC`, nothing is left half done, new loads are refused until a
write succeeds again, and everything already stored is still served.
"""

from __future__ import annotations

import errno
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot
from tests.support.gating import GatedLoad
from tests.support.small_disk import fill, mounted


class Provider:
    """A durable provider on a small disk, its load and unload journal, and a consumer."""

    def __init__(self, disk: Path) -> None:
        uid = uuid.uuid4().hex[:8]
        self.path = disk / "erm.db"
        self.config = rr.RegistrarConfig(
            name=f"erm-{uid}", backup_path=self.path, save_on_modify=True
        )
        self.loads: list[Any] = []
        self.unloads: list[Any] = []
        self.unloaded = threading.Event()
        self.registrar = rr.ResourceRegistrar.start(self.config)
        self.registrar.register_server("cam", load=self.load, unload=self.unload)
        self.consumer = rr.ResourceRegistrar.start(f"app-{uid}")

    def load(self, request: Any) -> Any:
        self.loads.append(request)
        return f"cam {request}"

    def unload(self, request: Any, _response: Any) -> None:
        self.unloads.append(request)
        self.unloaded.set()

    def call(self, request: Any, **kwargs: Any) -> rr.Query:
        return self.consumer.call(self.config.name, "cam", request, timeout=5, **kwargs)

    def stop(self) -> None:
        self.consumer.stop()
        self.registrar.stop()  # (each test makes room again before it ends)


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Path]:
    with mounted(tmp_path / "disk", size="1m") as where:
        yield where


@pytest.fixture
def provider(disk: Path) -> Iterator[Provider]:
    made = Provider(disk)
    yield made
    (disk / "filler").unlink(missing_ok=True)  # room again: the stop writes what waits
    made.stop()


def _full(disk: Path) -> Path:
    return fill(disk)


def test_a_new_load_on_a_full_disk_fails_at_once_naming_the_file_and_enospc(
    provider: Provider, disk: Path
) -> None:
    _full(disk)

    with pytest.raises(rr.CatalogWriteError) as raised:
        provider.call("a")

    assert str(provider.path) == raised.value.path
    assert errno.ENOSPC == raised.value.errno
    assert [] == provider.loads  # nothing was loaded: it could not have been recorded
    assert () == catalog_snapshot(provider.registrar).resources
    assert [] == provider.consumer.client_queries()


def test_a_shared_load_on_a_full_disk_is_refused_and_the_stored_one_still_served(
    provider: Provider, disk: Path
) -> None:
    held = provider.call("a")
    heard = threading.Event()
    provider.consumer.set_status_callback(held.id, lambda _q, _u: heard.set())
    _full(disk)

    with pytest.raises(rr.CatalogWriteError):
        provider.call("a")  # a second consumer cannot be recorded

    assert [held.id] == [q.id for q in provider.registrar.server_queries("cam")]
    provider.registrar.send_status(held.id, rr.Status.WARNING, "disk full", timeout=5)
    assert heard.wait(5)  # what is stored is served
    assert [held.id] == [q.id for q in provider.consumer.fetch_queries(provider.config.name, "cam")]


def test_an_unload_on_a_full_disk_is_refused_and_changes_nothing(
    provider: Provider, disk: Path
) -> None:
    held = provider.call("a")
    _full(disk)

    with pytest.raises(rr.CatalogWriteError):
        provider.consumer.unload(held.id)

    assert [held.id] == [q.id for q in provider.registrar.server_queries("cam")]
    assert [held.id] == [q.id for q in provider.consumer.client_queries()]
    assert [] == provider.unloads


def test_loads_are_served_again_once_a_write_succeeds(provider: Provider, disk: Path) -> None:
    filler = _full(disk)
    with pytest.raises(rr.CatalogWriteError):
        provider.call("a")

    filler.unlink()  # room again: the next load retries the write first
    query = provider.call("a")

    assert "cam a" == query.response
    provider.registrar.stop()  # then restored from what was written
    provider.registrar = rr.ResourceRegistrar.start(
        provider.config,
        setup=lambda r: r.register_server("cam", load=provider.load, unload=provider.unload),
    )
    assert [query.id] == [q.id for q in provider.registrar.server_queries("cam")]


def test_a_load_that_cannot_be_recorded_when_it_finishes_is_unloaded_and_fails_its_caller(
    provider: Provider, disk: Path
) -> None:
    slow = GatedLoad(threading.Event(), threading.Event(), lambda request: f"slow {request}")
    entered, gate = slow.started, slow.gate
    provider.registrar.register_server("slow", load=slow, unload=provider.unload)
    outcome: list[Any] = []

    def call() -> None:
        try:
            outcome.append(provider.consumer.call(provider.config.name, "slow", "b", timeout=10))
        except rr.RrError as exc:
            outcome.append(exc)

    caller = threading.Thread(target=call)
    caller.start()
    assert entered.wait(10)
    filler = _full(disk)  # the load started on record; its end cannot be written
    gate.set()
    caller.join(10)

    assert [rr.CatalogWriteError] == [type(o) for o in outcome]
    assert provider.unloaded.wait(10)  # what the load started is not left behind
    assert ["b"] == provider.unloads
    filler.unlink()
    assert [] == provider.registrar.server_queries("slow")


def test_a_durable_consumer_on_a_full_disk_fails_its_call_before_the_load_leaves(
    disk: Path, tmp_path: Path
) -> None:
    uid = uuid.uuid4().hex[:8]
    provider = rr.ResourceRegistrar.start(f"erm-{uid}")
    loads: list[Any] = []
    provider.register_server("cam", load=loads.append, unload=lambda _q, _r: None)
    consumer = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"app-{uid}", backup_path=disk / "app.db", save_on_modify=True)
    )
    try:
        filler = _full(disk)

        with pytest.raises(rr.CatalogWriteError):
            consumer.call(provider.name, "cam", "a", timeout=5)

        assert [] == loads  # its record could not be written, so the Load never left
        assert [] == provider.server_queries("cam")
        filler.unlink()
    finally:
        consumer.stop(timeout=5)
        provider.stop()


def test_a_stop_on_a_full_disk_stops_and_tells_its_caller_what_was_not_written(
    disk: Path,
) -> None:
    uid = uuid.uuid4().hex[:8]
    config = rr.RegistrarConfig(name=f"erm-{uid}", backup_path=disk / "e.db")
    provider = rr.ResourceRegistrar.start(config)  # (saves on an interval, and at stop)
    consumer = rr.ResourceRegistrar.start(f"app-{uid}")
    provider.register_server("cam", load=lambda r: r, unload=lambda _q, _r: None)
    consumer.call(config.name, "cam", "a" * 300_000)  # held, and not written yet
    filler = _full(disk)
    try:
        with pytest.raises(rr.CatalogWriteError):
            provider.stop(timeout=5)
        assert not provider.is_alive()
    finally:
        filler.unlink()
        consumer.stop()
