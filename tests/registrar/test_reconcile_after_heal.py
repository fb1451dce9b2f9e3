"""Rule 20 after a healed link: `peer_reachable` makes the consumer reconcile, retried.

A token that is back is not yet a peer that answers: the consumer's `Reconcile` is
retried (bounded backoff) until the provider answers, it is lost, or the consumer
stops. On one machine a provider "cannot answer" between its SIGKILL and its start
again; the restarts here are by hand, without a backup, so the provider does not
reconcile by itself, and only the consumer's retries can settle what it lost.
"""

from __future__ import annotations

import itertools
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors._registrar.life import RETRY_FIRST, RETRY_MAX, retry_delay
from rr_actors.testing import (
    RemoteRegistrar,
    SharedObjects,
    System,
    expect_restart,
    intercept,
)
from tests.support.names import named
from tests.support.waiting import wait_for

pytestmark = [
    pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals"),
    pytest.mark.usefixtures("by_value"),  # (tests/conftest.py)
]


def leaf_setup(unloads: Any) -> Callable[[rr.ResourceRegistrar], None]:
    def setup(registrar: rr.ResourceRegistrar) -> None:
        registrar.register_server(
            "leaf", load=lambda r: {"for": r}, unload=lambda r, _s: unloads.append(r)
        )

    return setup


def test_the_reconcile_backoff_doubles_up_to_its_bound() -> None:
    delays = [retry_delay(n) for n in range(1, 12)]

    assert RETRY_FIRST == delays[0]
    assert all(b == min(2 * a, RETRY_MAX) for a, b in itertools.pairwise(delays))
    assert RETRY_MAX == max(delays) == retry_delay(10**6)


def test_ids_the_provider_lost_are_fatal_once_the_retried_reconcile_is_answered(
    system: System, started: list[rr.ResourceRegistrar], process_helpers: SharedObjects
) -> None:
    unloads = process_helpers.list()
    name = named("provider")
    provider = RemoteRegistrar.start(name, system, setup=leaf_setup(unloads))
    consumer = rr.ResourceRegistrar.start(named("consumer"), network=system)
    started.append(consumer)
    heard: list[Any] = []
    retries = threading.Event()
    intercept(consumer, "reconcile_retry", before=lambda _m: retries.set())
    query = consumer.call(name, "leaf", "camera", timeout=10)
    consumer.set_status_callback(query.id, lambda q, u: heard.append((q.id, u.status)))

    with expect_restart(name):  # down for a moment: not lost (no death watch)
        provider.kill()
    Served(consumer).peer_reachable(name)  # its token is back, it does not answer yet
    assert retries.wait(5)  # the first reconcile failed: retried
    assert [] == heard
    back = RemoteRegistrar.start(name, system, setup=leaf_setup(unloads))  # lost everything
    try:
        assert wait_for(lambda: len(heard) > 0, 10)
        consumer.client_queries()

        assert [(query.id, rr.Status.FATAL)] == heard
        assert [] == consumer.client_queries()
    finally:
        back.stop()


def test_an_id_released_while_the_provider_could_not_answer_is_unloaded_once_it_answers(
    system: System,
    started: list[rr.ResourceRegistrar],
    process_helpers: SharedObjects,
    tmp_path: Path,
) -> None:
    unloads = process_helpers.list()
    config = rr.RegistrarConfig(
        named("provider"), backup_path=tmp_path / "provider.db", save_on_modify=True
    )
    provider = RemoteRegistrar.start(config, system, setup=leaf_setup(unloads))
    consumer = rr.ResourceRegistrar.start(
        named("consumer"),
        setup=lambda r: r.register_server(
            "composite",
            load=lambda req: r.call(config.name, "leaf", req, timeout=10).response,
            unload=lambda _r, _s: None,
        ),
        network=system,
    )
    app = rr.ResourceRegistrar.start(named("app"))
    started.extend([consumer, app])
    top = app.call(consumer.name, "composite", "camera", timeout=10)
    assert 1 == len(provider.server_queries("leaf"))

    with expect_restart(config.name):
        provider.kill()
    app.unload(top.id, timeout=10)  # its dependency's release cannot reach the provider
    assert [] == consumer.client_queries()
    Served(consumer).peer_reachable(config.name)
    back = RemoteRegistrar.start(config, system, setup=leaf_setup(unloads))
    try:
        assert wait_for(lambda: len(unloads) > 0, 10)
        Served(consumer).peer_reachable(config.name)  # told again: nothing more to do
        consumer.client_queries()
        assert wait_for(lambda: [] == back.server_queries("leaf"), 10)

        assert ["camera"] == list(unloads)  # once, whoever reconciled first
    finally:
        back.stop()


def test_a_consumer_that_stops_while_it_retries_stops_cleanly_and_retries_no_more(
    system: System, process_helpers: SharedObjects
) -> None:
    unloads = process_helpers.list()
    name = named("provider")
    provider = RemoteRegistrar.start(name, system, setup=leaf_setup(unloads))
    consumer = rr.ResourceRegistrar.start(named("consumer"), network=system)
    retries = threading.Event()
    intercept(consumer, "reconcile_retry", before=lambda _m: retries.set())
    consumer.call(name, "leaf", "camera", timeout=10)
    with expect_restart(name):
        provider.kill()
    Served(consumer).peer_reachable(name)
    assert retries.wait(5)

    consumer.stop(timeout=5)  # its release cannot reach the provider: it goes anyway

    assert not consumer.is_alive()
