"""Calls racing a stop, a give-up, a retry, or a store that cannot hold a value."""

from __future__ import annotations

import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pykka
import pytest

import rr_actors as rr
import rr_actors._registrar
from rr_actors._actors import OneShotFuture
from rr_actors._registrar import RegistrarActor, _Request
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


# -- a caller that stops waiting, and the answers that come anyway ------------------------------


def _left_behind(registrar: rr.ResourceRegistrar) -> tuple[set[str], set[str]]:
    """Query ids the registrar still expects an answer for, and ones notices wait for."""
    state = FutureReply()
    registrar._ref.tell(
        _Request(
            lambda actor, reply: reply.set_result(
                (set(actor.due._attempts), set(actor.parked_notices))
            ),
            state,
        )
    )
    left: tuple[set[str], set[str]] = state.future.get(timeout=10)
    return left


def _busy(registrar: rr.ResourceRegistrar) -> tuple[threading.Event, FutureReply]:
    """Keep the registrar's actor busy until the returned gate is set (a slow provider)."""
    gate, busy = threading.Event(), FutureReply()
    registrar._ref.tell(_Request(lambda _actor, reply: reply.set_result(gate.wait(10)), busy))
    return gate, busy


def test_a_call_interrupted_by_ctrl_c_leaves_nothing_behind(
    started: Callable[..., rr.ResourceRegistrar],
) -> None:
    # The interrupted caller never records its answer: it withdraws the call (claims its
    # future, tells its registrar, sends the provider an Abandon) before the exception
    # leaves `call`. Its answer, when it comes, is dropped.
    assert threading.current_thread() is threading.main_thread()
    provider, consumer = started("provider"), started("consumer")
    entered, release = threading.Event(), threading.Event()

    def load(request: Any) -> Any:
        entered.set()
        assert release.wait(10)
        return f"loaded {request}"

    provider.register_server("slow", load=load, unload=lambda _request, _response: None)

    def interrupt() -> None:
        assert entered.wait(10)
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

    interrupter = threading.Thread(target=interrupt)
    interrupter.start()
    with pytest.raises(KeyboardInterrupt):
        consumer.call(provider.name, "slow", "x", timeout=10)
    interrupter.join(10)
    release.set()
    second = consumer.call(provider.name, "slow", "x", timeout=10)  # the same load's answer

    assert [second.id] == [q.id for q in provider.server_queries("slow")]
    assert [second.id] == [q.id for q in consumer.client_queries()]
    assert (set(), set()) == _left_behind(consumer)
    provider.send_status(second.id, rr.Status.WARNING, "hot", timeout=5)
    provider.unregister_server("slow", timeout=5)
    assert [] == consumer.client_queries()


@pytest.mark.parametrize("durable", [False, True], ids=["plain", "save_on_modify"])
def test_a_timed_out_retry_of_a_held_id_leaves_both_ends_agreeing(
    started: Callable[..., rr.ResourceRegistrar], tmp_path: Path, durable: bool
) -> None:
    provider = started("provider")
    config = {"backup_path": tmp_path / "c.db", "save_on_modify": True} if durable else {}
    consumer = started("consumer", **config)
    provider.register_server("leaf", load=lambda r: f"loaded {r}", unload=lambda _q, _r: None)
    first = consumer.call(provider.name, "leaf", "x")
    gate, busy = _busy(provider)  # the provider answers the retry only after its timeout

    with pytest.raises(rr.CallTimeoutError):
        consumer.call(provider.name, "leaf", "x", query_id=first.id, timeout=0.3)
    gate.set()
    assert busy.future.get(timeout=10) is True

    provider_holds = [q.id for q in provider.server_queries("leaf")]  # after Load, Abandon
    assert provider_holds == [q.id for q in consumer.client_queries()]  # after the answer
    assert (set(), set()) == _left_behind(consumer)


class _ErrorAsTheWaitRunsOut(OneShotFuture):
    """A caller's future whose wait runs out while an error answer is being set."""

    def __init__(self) -> None:
        super().__init__()
        self.erring = threading.Event()
        self.withdrawn = threading.Event()

    def wait(self, timeout: float | None = None) -> bool:
        if timeout is None:
            return super().wait()
        assert self.erring.wait(10)  # the error answer is on its way...
        return False  # ...as the caller's wait runs out

    def set(self, value: Any = None) -> None:
        super().set(value)
        self.withdrawn.set()

    def set_exception(self, exc_info: Any = None) -> None:
        self.erring.set()
        assert self.withdrawn.wait(10)  # the caller claims first
        super().set_exception(exc_info)


def test_an_error_answer_that_loses_to_the_timeout_leaves_nothing_behind(
    started: Callable[..., rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
) -> None:
    provider, consumer = started("provider"), started("consumer")

    def load(request: Any) -> Any:
        raise ValueError(request)

    provider.register_server("bad", load=load, unload=lambda _request, _response: None)
    monkeypatch.setattr(rr_actors._registrar, "OneShotFuture", _ErrorAsTheWaitRunsOut)

    with pytest.raises(rr.CallTimeoutError):
        consumer.call(provider.name, "bad", "x", timeout=5)

    assert [] == consumer.client_queries()
    assert (set(), set()) == _left_behind(consumer)


def test_an_answer_recorded_as_the_consumer_stops_is_given_back(
    started: Callable[..., rr.ResourceRegistrar], monkeypatch: pytest.MonkeyPatch
) -> None:
    # The caller tells its registrar the answer while the actor, stopping, is past its
    # last look at the mailbox (it took the stop message) but not yet marked stopped:
    # the tell lands after the loop ended, and the id must still be given back.
    provider, consumer = started("provider"), started("consumer")
    entered, release = threading.Event(), threading.Event()
    in_stop, resume = threading.Event(), threading.Event()

    def load(request: Any) -> Any:
        entered.set()
        assert release.wait(10)
        return request

    provider.register_server("slow", load=load, unload=lambda _request, _response: None)
    original = RegistrarActor._stop

    def paused_stop(self: RegistrarActor) -> None:
        if self.name == consumer.name:
            in_stop.set()
            assert resume.wait(10)
        original(self)

    monkeypatch.setattr(RegistrarActor, "_stop", paused_stop)
    outcome: list[Any] = []
    caller = threading.Thread(
        target=lambda: outcome.append(consumer.call(provider.name, "slow", "x", timeout=10))
    )
    caller.start()
    assert entered.wait(10)
    stopper = threading.Thread(target=consumer.stop)
    stopper.start()
    assert in_stop.wait(10)
    release.set()
    caller.join(10)  # its _ClientLoaded went into the mailbox of an actor still "alive"
    resume.set()
    stopper.join(10)

    assert isinstance(outcome[0], rr.Query)
    assert [] == provider.server_queries("slow")
