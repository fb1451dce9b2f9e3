"""`stop()` waits for the unloads under way at its registrar, bounded (issue 32 item 1.7).

A clean stop waits for its own resources' unload callbacks still running for at most
`STOP_WAITS_FOR_UNLOADS` of its timeout: one that returns within it is written as
unloaded before `stop()` returns; one that hangs past it is cut short (`UnloadCutShort`),
the stop returns in its time, and the resource is in doubt at the next start (rule 16).
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors import events
from rr_actors._registrar.handle import STOP_WAITS_FOR_UNLOADS
from rr_actors.testing import catalog_snapshot, intercept


class Heard:
    """The events a subscription delivers, in order."""

    def __init__(self) -> None:
        self.events: list[events.Event] = []
        self.lock = threading.Lock()

    def __call__(self, event: events.Event) -> None:
        with self.lock:
            self.events.append(event)

    def kinds(self) -> list[str]:
        with self.lock:
            return [type(e).__name__ for e in self.events]


class Gated:
    """A server "leaf" whose unload callback says it started, then waits for `gate`."""

    def __init__(self) -> None:
        self.entered, self.gate = threading.Event(), threading.Event()
        self.unloaded: list[Any] = []

    def unload(self, request: Any, _response: Any) -> None:
        self.entered.set()
        assert self.gate.wait(30)
        self.unloaded.append(request)


@pytest.fixture
def gated(tmp_path: Path) -> Iterator[tuple[rr.ResourceRegistrar, rr.ResourceRegistrar, Gated]]:
    """A provider with a backup serving "leaf", a consumer, and the gate of its unloads."""
    uid = uuid.uuid4().hex[:8]
    config = rr.RegistrarConfig(f"erm-{uid}", backup_path=tmp_path / "erm.db")
    provider = rr.ResourceRegistrar.start(config)
    consumer = rr.ResourceRegistrar.start(rr.RegistrarConfig(f"app-{uid}"))
    server = Gated()
    provider.register_server("leaf", load=lambda r: {"for": r}, unload=server.unload)
    yield provider, consumer, server
    server.gate.set()
    consumer.stop()
    provider.stop()


def unloading(
    provider: rr.ResourceRegistrar, consumer: rr.ResourceRegistrar, server: Gated
) -> tuple[str, threading.Thread, list[str]]:
    """Load "x", then release it from another thread: its unload callback is running.

    Returns the resource's id, the releasing thread and what its `unload` ended with.
    """
    query = consumer.call(provider.name, "leaf", "x", timeout=10)
    ended: list[str] = []

    def release() -> None:
        try:
            consumer.unload(query.id, timeout=30)
        except rr.RrError as exc:
            ended.append(type(exc).__name__)
        else:
            ended.append("released")

    releasing = threading.Thread(target=release)
    releasing.start()
    assert server.entered.wait(10)
    (resource,) = catalog_snapshot(provider).resources
    return resource.id, releasing, ended


def restored_in_doubt(config: rr.RegistrarConfig) -> list[str]:
    """The ids in doubt in the backup of `config` (restored and stopped again)."""
    again = rr.ResourceRegistrar.start(config)
    try:
        return [q.id for q in again.in_doubt]
    finally:
        again.stop()


def test_stop_waits_for_an_unload_under_way_that_returns_within_its_bound(
    gated: tuple[rr.ResourceRegistrar, rr.ResourceRegistrar, Gated],
) -> None:
    provider, consumer, server = gated
    config = provider.config
    _rid, releasing, ended = unloading(provider, consumer, server)
    heard = Heard()
    subscription = provider.subscribe(heard)
    # The unload returns once the stop has begun (its message was handled): the stop
    # has released what it held and waits for the unload.
    with intercept(provider, "stop", after=lambda _message: server.gate.set()):
        provider.stop(timeout=20)
    releasing.join(10)

    assert ["x"] == server.unloaded  # it returned before stop() did
    assert ["released"] == ended  # and its consumer was answered
    assert subscription.wait_delivered(timeout=5)
    kinds = heard.kinds()
    assert "UnloadCutShort" not in kinds
    assert kinds.index("ResourceUnloaded") < kinds.index("RegistrarStopped")
    assert [] == restored_in_doubt(config)  # written as unloaded


def test_stop_cuts_short_an_unload_that_hangs_past_its_bound(
    gated: tuple[rr.ResourceRegistrar, rr.ResourceRegistrar, Gated],
) -> None:
    provider, consumer, server = gated
    config = provider.config
    rid, releasing, ended = unloading(provider, consumer, server)
    heard = Heard()
    subscription = provider.subscribe(heard)
    timeout = 2.0
    started = time.monotonic()
    provider.stop(timeout=timeout)  # (raises CallTimeoutError past its timeout)
    waited = time.monotonic() - started

    assert waited >= timeout * STOP_WAITS_FOR_UNLOADS * 0.9  # it waited for the unload
    assert [] == server.unloaded  # still running
    assert subscription.wait_delivered(timeout=5)
    cut = [e for e in heard.events if isinstance(e, events.UnloadCutShort)]
    assert [(provider.name, "leaf", rid)] == [(e.registrar, e.server, e.resource_id) for e in cut]
    kinds = heard.kinds()
    assert "ResourceUnloaded" not in kinds
    assert kinds.index("UnloadCutShort") < kinds.index("RegistrarStopped")
    server.gate.set()  # the callback returns now: its answer goes nowhere
    releasing.join(10)
    assert ["RegistrarStoppedError"] == ended  # its consumer gave the id up
    assert [rid] == restored_in_doubt(config)  # in doubt at the next start
