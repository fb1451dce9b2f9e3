"""Calls racing a stop, a give-up, a retry, or a store that cannot hold a value."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pykka
import pytest

import rr_actors as rr
from rr_actors._actors import OneShotFuture
from rr_actors._catalog import ClientRecord
from rr_actors._registrar import _CallFailed, _ClientLoaded, _Request
from rr_actors._replies import FutureReply
from rr_actors.testing import catalog_snapshot


@pytest.fixture
def started() -> Iterator[Callable[..., rr.ResourceRegistrar]]:
    """Start registrars with unique names; stop them all at the end."""
    registrars: list[rr.ResourceRegistrar] = []

    def start(prefix: str, **config: Any) -> rr.ResourceRegistrar:
        name = f"{prefix}-{uuid.uuid4().hex[:8]}"
        registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, **config))
        registrars.append(registrar)
        return registrar

    yield start
    for registrar in reversed(registrars):
        registrar.stop()


def _in_thread(fn: Callable[[], Any]) -> tuple[threading.Thread, list[Any]]:
    outcome: list[Any] = []

    def run() -> None:
        try:
            outcome.append(fn())
        except Exception as exc:  # the test inspects what was raised
            outcome.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    return thread, outcome


def _gated_server(registrar: rr.ResourceRegistrar) -> tuple[threading.Event, threading.Event]:
    """A server `slow` whose load waits for the returned gate; `entered` is set on entry."""
    entered, gate = threading.Event(), threading.Event()

    def load(request: Any) -> Any:
        entered.set()
        assert gate.wait(10)
        return f"loaded {request}"

    registrar.register_server("slow", load=load, unload=lambda r, s: None)
    return entered, gate


def test_stopping_a_provider_fails_the_calls_waiting_on_its_loads_at_once(started: Any) -> None:
    provider, consumer = started("erm"), started("app")
    entered, gate = _gated_server(provider)
    try:
        thread, outcome = _in_thread(lambda: consumer.call(provider.name, "slow", 1, timeout=30))
        assert entered.wait(5)
        began = time.monotonic()
        provider.stop(timeout=5)
        thread.join(5)

        assert [rr.RegistrarStoppedError] == [type(o) for o in outcome]
        assert time.monotonic() - began < 5.0  # not the call's 30 s timeout
    finally:
        gate.set()


def test_stopping_a_durable_consumer_fails_its_call_in_flight_and_frees_the_id(
    started: Any, tmp_path: Path
) -> None:
    provider = started("erm")
    consumer = started("app", backup_path=tmp_path / "app.db", save_on_modify=True)
    entered, gate = _gated_server(provider)
    thread, outcome = _in_thread(lambda: consumer.call(provider.name, "slow", 1, timeout=30))
    assert entered.wait(5)
    consumer.stop(timeout=5)
    thread.join(5)
    gate.set()

    assert [rr.RegistrarStoppedError] == [type(o) for o in outcome]
    catalog_snapshot(provider)  # its invariants hold
    assert _wait_for(lambda: [] == provider.server_queries("slow"))


def test_a_timed_out_call_held_during_setup_is_never_loaded(started: Any) -> None:
    consumer = started("app")
    name = f"erm-{uuid.uuid4().hex[:8]}"
    in_setup, finish_setup = threading.Event(), threading.Event()
    loads: list[Any] = []

    def setup(registrar: rr.ResourceRegistrar) -> None:
        in_setup.set()
        assert finish_setup.wait(10)
        registrar.register_server(
            "s", load=lambda r: loads.append(r) or r, unload=lambda r, s: None
        )

    starter, providers = _in_thread(lambda: rr.ResourceRegistrar.start(name, setup=setup))
    try:
        assert in_setup.wait(5)
        with pytest.raises(rr.CallTimeoutError):
            consumer.call(name, "s", 1, timeout=0.3)
        finish_setup.set()
        starter.join(5)
        provider = providers[0]
        later = consumer.call(name, "s", 2, timeout=5)  # a call after the give-up arrived

        assert ([2], [later.id]) == (loads, [q.id for q in provider.server_queries("s")])
    finally:
        finish_setup.set()
        starter.join(5)
        for provider in providers:
            if isinstance(provider, rr.ResourceRegistrar):
                provider.stop()


def test_a_retry_with_the_same_query_id_after_a_timeout_is_held_once_and_unloads(
    started: Any,
) -> None:
    provider, consumer = started("erm"), started("app")
    entered, gate = _gated_server(provider)
    with pytest.raises(rr.CallTimeoutError):
        consumer.call(provider.name, "slow", 1, timeout=0.3, query_id="q-1")
    assert entered.wait(5)
    gate.set()
    retried = consumer.call(provider.name, "slow", 1, timeout=5, query_id="q-1")

    assert ["q-1"] == [q.id for q in consumer.client_queries()]
    assert ["q-1"] == [q.id for q in provider.server_queries("slow")]
    consumer.unload(retried.id)
    assert [] == provider.server_queries("slow")


def test_an_unpicklable_response_fails_that_load_and_a_durable_provider_keeps_serving(
    started: Any, tmp_path: Path
) -> None:
    provider = started("erm", backup_path=tmp_path / "erm.db", save_on_modify=True)
    consumer = started("app")
    provider.register_server("lock", load=lambda r: threading.Lock(), unload=lambda r, s: None)
    provider.register_server("echo", load=lambda r: r, unload=lambda r, s: None)

    with pytest.raises(rr.ResourceLoadError, match="cannot be pickled"):
        consumer.call(provider.name, "lock", 1, timeout=5)
    assert "fine" == consumer.call(provider.name, "echo", "fine", timeout=5).response
    assert [] == provider.server_queries("lock")


def test_an_unpicklable_request_to_a_durable_provider_is_a_config_error(
    started: Any, tmp_path: Path
) -> None:
    provider = started("erm", backup_path=tmp_path / "erm.db", save_on_modify=True)
    consumer = started("app")
    provider.register_server("echo", load=lambda r: "ok", unload=lambda r, s: None)

    with pytest.raises(rr.ConfigError, match="cannot be pickled"):
        consumer.call(provider.name, "echo", threading.Lock(), timeout=5)
    assert provider.is_alive()


def _wait_for(condition: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Ask `condition()` again until it holds (each ask is a round trip to an actor)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
    return False


def test_a_pykka_ask_that_arrives_while_the_registrar_stops_is_answered(
    started: Callable[..., rr.ResourceRegistrar],
) -> None:
    # The handle's stop() ends with pykka's `ref.stop()`, an ask; `op_stop` drains the
    # mailbox to fail whoever waits. An ask in that mailbox must hear, not be dropped.
    registrar = started("stopping")
    gate = threading.Event()
    busy, stopping = FutureReply(), FutureReply()
    registrar._ref.tell(_Request(lambda _actor, reply: reply.set_result(gate.wait(10)), busy))
    registrar._ref.tell(_Request(lambda actor, reply: actor.op_stop(reply), stopping))
    asked = registrar._ref.ask("anything", block=False)  # queued behind the stop

    gate.set()

    assert stopping.future.get(timeout=10) is None
    with pytest.raises(pykka.ActorDeadError):
        asked.get(timeout=10)


def test_a_give_up_that_arrives_after_its_answer_was_recorded_is_not_remembered(
    started: Callable[..., rr.ResourceRegistrar],
) -> None:
    # A caller that timed out tells its registrar `_CallFailed(gave_up=True)`; the
    # answering thread may have told the answer first. Nothing more comes for that
    # attempt, so nothing may wait for it in `given_up` (it would stay there for good).
    consumer = started("consumer")
    attempt = OneShotFuture()
    query = rr.Query(str(uuid.uuid4()), "leaf", "provider-gone", consumer.name, "x", "r")
    consumer._ref.tell(_ClientLoaded(ClientRecord(query, None, loaded=True), None, attempt))
    consumer._ref.tell(_CallFailed(query.id, attempt, gave_up=True))
    state = FutureReply()
    consumer._ref.tell(
        _Request(
            lambda actor, reply: reply.set_result(
                (set(actor.given_up), set(actor.catalog.clients))
            ),
            state,
        )
    )

    assert (set(), set()) == state.future.get(timeout=10)
