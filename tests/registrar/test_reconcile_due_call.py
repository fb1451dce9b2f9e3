"""Rule 20: what a consumer's `Reconcile` lists, and what it makes of the answer.

A call due as the consumer reconciles is decided by its own answer.

After a healed link the consumer's `Reconcile` lists the calls whose answer is due, but
a caller's `Load` may leave after the `Reconcile` (over Zenoh its thread may still be
asking the network where the provider is). The provider then answers that id "unknown":
it has not seen the `Load` yet. Found across two hosts: the call succeeded, its answer
was recorded before the `Reconcile`'s, and the consumer reported its fresh id `FATAL`
and forgot it (`unload` raised `UnknownQueryError`).

A call refused at once (its provider is known to be gone: nothing was sent) is not held
for a retry: nothing there can hold its id. Found across two hosts: a consumer that retried
its call during a cut link listed ~900 such ids in the `Reconcile` after the heal (a 40 KB
message, every retry's id).
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._registrar import Served
from rr_actors.testing import crash, expect_restart, intercept


@pytest.fixture
def started() -> Iterator[Callable[[str], rr.ResourceRegistrar]]:
    registrars: list[rr.ResourceRegistrar] = []

    def start(prefix: str) -> rr.ResourceRegistrar:
        name = f"{prefix}-{uuid.uuid4().hex[:8]}"
        registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name))
        registrars.append(registrar)
        return registrar

    yield start
    for registrar in reversed(registrars):
        registrar.stop()


def test_a_call_whose_load_leaves_after_the_reconcile_keeps_its_id(
    started: Callable[[str], rr.ResourceRegistrar],
) -> None:
    provider, consumer = started("prov"), started("cons")
    unloads: list[Any] = []
    provider.register_server("leaf", load=lambda r: r, unload=lambda r, _s: unloads.append(r))
    consumer.call(provider.name, "leaf", "held")  # the consumer holds ids there: it reconciles
    statuses: list[rr.StatusUpdate] = []
    qid = str(uuid.uuid4())
    due, reconciled, returned = threading.Event(), threading.Event(), threading.Event()

    def hold_load(load: Any) -> None:
        if load.query_id == qid:  # due now; its Load leaves once the provider reconciled
            due.set()
            assert reconciled.wait(10)

    def hold_consumer(_message: Any) -> None:
        assert returned.wait(10)  # the call's answer is handed over before the Reconcile's

    outcome: list[Any] = []

    def call() -> None:
        try:
            outcome.append(
                consumer.call(
                    provider.name,
                    "leaf",
                    "fresh",
                    query_id=qid,
                    on_status=lambda _q, update: statuses.append(update),
                    timeout=10,
                )
            )
        finally:
            returned.set()

    with (
        intercept(consumer, "send_load", before=hold_load),
        intercept(provider, "reconcile", after=lambda _m: reconciled.set()),
        intercept(consumer, "peer_reachable", after=hold_consumer),
    ):
        caller = threading.Thread(target=call)
        caller.start()
        assert due.wait(10)
        Served(consumer).peer_reachable(provider.name)  # a healed link: it reconciles
        caller.join(10)
        consumer.client_queries()  # the Reconcile's answer was handled

    assert [qid] == [query.id for query in outcome]
    assert [] == statuses  # no FATAL: the provider holds it
    assert qid in [query.id for query in consumer.client_queries()]
    consumer.unload(qid)
    provider.server_queries("leaf")  # (its Unload was handled)
    assert ["fresh"] == unloads


def test_a_call_refused_at_once_is_not_listed_when_the_consumer_reconciles(
    started: Callable[[str], rr.ResourceRegistrar],
) -> None:
    provider, consumer = started("prov"), started("cons")
    name = provider.name
    with expect_restart(name):  # down for a moment, not lost: its consumers keep waiting
        crash(provider)
    for _ in range(3):
        with pytest.raises(rr.RegistrarUnavailableError):
            consumer.call(name, "leaf", "x", timeout=5)  # refused at once: nothing sent
    back = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name))
    try:
        back.register_server("leaf", load=lambda r: r, unload=lambda _r, _s: None)
        listed: list[tuple[str, ...]] = []
        intercept(back, "reconcile", before=lambda message: listed.append(message.held))

        Served(consumer).peer_reachable(name)  # a healed link: it reconciles if it holds ids
        consumer.client_queries()  # (its PeerReachable was handled)
        back.server_queries("leaf")  # (and a Reconcile it was sent)

        assert [] == listed  # it holds nothing there
    finally:
        back.stop()
