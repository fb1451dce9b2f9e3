"""A registrar's actor never waits on the network (the Zenoh carrier).

The test process attaches, as a manager process does, to a router in a child process
and serves a registrar. The router is then frozen (SIGSTOP; its lease is long, so the
link stays up): whatever this process asks of the network waits until the router runs
again. A message the registrar's actor sends to a registrar this process does not see
served (never heard of, or heard to die) must not hold the actor: it answers other
messages meanwhile (a heartbeat comes that way), and the message's fate (nobody serves
that name; or it is delivered, in order) is known once the network answers.

A registrar whose token is "still on its way" here is one whose liveliness samples this
process's presence ignores (`Presence._on_live` wrapped before the member starts): it
is heard only when the network is asked, as after a restart, or a join, under load.
Order, not speed: each test checks that the actor answered before the router ran again.
"""

from __future__ import annotations

import contextlib
import multiprocessing.connection
import multiprocessing.context
import os
import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pykka
import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import FutureReply
from rr_actors._transport.zenoh import presence
from rr_actors.testing import run_on_actor
from rr_actors.testing.carrier import Fetch, Revoke, Served

LEASE = 60.0
"""Seconds of the router's lease: longer than the test, so a frozen router's link stays."""


def router_main(system: str, serves: str, control: multiprocessing.connection.Connection) -> None:
    """A router of `system` (lease `LEASE`) that serves registrar `serves` (with a server
    `s`), sends its address, then waits to stop."""
    network = rr.ZenohNetwork(system=system, tls=None, lease=LEASE)
    registrar = rr.ResourceRegistrar.start(serves)
    try:
        registrar.register_server("s", load=lambda request: request, unload=lambda *_: None)
        network.serve(Served(registrar))
        control.send(network.address)
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        registrar.stop()
        network.close()


SERVED = f"there-{uuid.uuid4().hex[:6]}"
"""The registrar the router process serves."""


@pytest.fixture
def frozen_router(
    context: multiprocessing.context.ForkServerContext,
) -> Iterator[tuple[Any, int]]:
    """A router process: `(its address, its pid)`; continued and stopped at the end."""
    parent_end, child_end = context.Pipe()
    process = context.Process(
        target=router_main,
        args=(f"test-{uuid.uuid4().hex[:8]}", SERVED, child_end),
        daemon=True,
    )
    process.start()
    child_end.close()
    try:
        assert parent_end.poll(30), "the router did not start"
        assert process.pid is not None
        yield parent_end.recv(), process.pid
    finally:
        with contextlib.suppress(OSError):
            os.kill(process.pid or 0, signal.SIGCONT)
        with contextlib.suppress(OSError):
            parent_end.send("stop")
        process.join(10)
        if process.is_alive():
            process.kill()
            process.join(5)
        parent_end.close()


def test_an_actor_answers_while_a_registrar_it_never_heard_of_is_asked_of_the_network(
    frozen_router: tuple[Any, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    address, router_pid = frozen_router
    monkeypatch.setattr(presence, "ASK_TIMEOUT", 30.0)  # an ask ends when the router answers
    member = address.attach()
    registrar = rr.ResourceRegistrar.start(f"here-{uuid.uuid4().hex[:6]}")
    unheard = f"nobody-{uuid.uuid4().hex[:6]}"
    fetched = FutureReply()
    try:
        member.serve(Served(registrar))
        os.kill(router_pid, signal.SIGSTOP)
        try:
            told = run_on_actor(
                registrar,
                lambda: DIRECTORY.lookup(unheard).tell(Fetch("s", registrar.name, fetched)),
            )
            answered = run_on_actor(registrar, lambda: "answered")

            # before the router runs again: the actor did not wait for the network
            assert "answered" == answered.get(timeout=10)
            told.get(timeout=0)  # told without an error, nothing decided yet
            with pytest.raises(pykka.Timeout):  # its fate waits for the network
                fetched.future.get(timeout=0)
        finally:
            os.kill(router_pid, signal.SIGCONT)

        with pytest.raises(rr.UnknownRegistrarError, match=f"no registrar named '{unheard}'"):
            fetched.future.get(timeout=40)
    finally:
        registrar.stop()
        member.close()


def test_an_actor_answers_while_a_message_without_reply_to_an_unheard_registrar_waits(
    frozen_router: tuple[Any, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A message that wants no answer (a `Revoke`, as an `Abandon` of a given-up call
    or the `ReconcileAsk` of a restart): dropped once nobody serves the name."""
    address, router_pid = frozen_router
    monkeypatch.setattr(presence, "ASK_TIMEOUT", 30.0)
    member = address.attach()
    registrar = rr.ResourceRegistrar.start(f"here-{uuid.uuid4().hex[:6]}")
    try:
        member.serve(Served(registrar))
        os.kill(router_pid, signal.SIGSTOP)
        try:
            told = run_on_actor(
                registrar,
                lambda: DIRECTORY.lookup(f"nobody-{uuid.uuid4().hex[:6]}").tell(Revoke(("q",))),
            )

            assert [] == registrar.client_queries(timeout=10)  # before the router runs
            told.get(timeout=0)
        finally:
            os.kill(router_pid, signal.SIGCONT)
    finally:
        registrar.stop()
        member.close()


class Ordered:
    """A reply that notes, in `answers`, its number and its answer when answered."""

    def __init__(self, number: int, answers: list[tuple[int, Any]], done: threading.Event) -> None:
        self.number = number
        self.answers = answers
        self.done = done

    def set_result(self, value: Any) -> None:
        self.answers.append((self.number, value))
        if len(self.answers) == 3:
            self.done.set()

    def set_error(self, error: BaseException) -> None:
        self.set_result(error)


def test_messages_an_actor_tells_a_registrar_not_heard_of_yet_arrive_in_order_once_it_is(
    frozen_router: tuple[Any, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    address, router_pid = frozen_router
    monkeypatch.setattr(presence, "ASK_TIMEOUT", 30.0)
    on_live = presence.Presence._on_live  # (bound when the member's presence starts)

    def late(self: presence.Presence, sample: Any) -> None:  # as if its token were on
        if SERVED not in str(sample.key_expr):  # the way still: heard only when asked
            on_live(self, sample)

    monkeypatch.setattr(presence.Presence, "_on_live", late)
    member = address.attach()
    registrar = rr.ResourceRegistrar.start(f"here-{uuid.uuid4().hex[:6]}")
    answers: list[tuple[int, Any]] = []
    all_answered = threading.Event()

    def fetch(number: int) -> None:
        reply = Ordered(number, answers, all_answered)
        DIRECTORY.lookup(SERVED).tell(Fetch("s", registrar.name, reply))

    try:
        member.serve(Served(registrar))
        assert SERVED not in member.names()
        os.kill(router_pid, signal.SIGSTOP)
        try:
            run_on_actor(registrar, lambda: fetch(1))
            run_on_actor(registrar, lambda: fetch(2))

            assert [] == registrar.client_queries(timeout=10)  # before the router runs
        finally:
            os.kill(router_pid, signal.SIGCONT)
        run_on_actor(registrar, lambda: fetch(3)).get(timeout=10)

        assert all_answered.wait(40)
    finally:
        registrar.stop()
        member.close()

    assert [(1, []), (2, []), (3, [])] == answers


def manager_main(address: Any, name: str, control: multiprocessing.connection.Connection) -> None:
    """A process that attaches through the router and serves registrar `name` (with a
    server `s`) until told on its control pipe."""
    member = address.attach()
    registrar = rr.ResourceRegistrar.start(name)
    try:
        registrar.register_server("s", load=lambda request: request, unload=lambda *_: None)
        member.serve(Served(registrar))
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        registrar.stop()
        member.close()


def test_an_actor_answers_while_its_message_to_a_registrar_heard_to_die_waits_for_the_network(
    frozen_router: tuple[Any, int],
    context: multiprocessing.context.ForkServerContext,
    monkeypatch: pytest.MonkeyPatch,
    eventually: Callable[..., bool],
) -> None:
    """Its restart serves already, its token not heard here yet: the message goes once
    the network says so, or fails as unavailable (what the network answers a client's
    liveliness query is not always all its router knows: the ask decides either way),
    never as unknown, never held."""
    address, router_pid = frozen_router
    monkeypatch.setattr(presence, "ASK_TIMEOUT", 30.0)
    name = f"restarted-{uuid.uuid4().hex[:6]}"
    hidden = threading.Event()  # from then on, its tokens are still on the way (heard
    on_live = presence.Presence._on_live  # only when asked)

    def late(self: presence.Presence, sample: Any) -> None:
        if not (hidden.is_set() and name in str(sample.key_expr)):
            on_live(self, sample)

    monkeypatch.setattr(presence.Presence, "_on_live", late)
    member = address.attach()
    registrar = rr.ResourceRegistrar.start(f"here-{uuid.uuid4().hex[:6]}")
    managers: list[tuple[Any, Any]] = []

    def manager() -> Any:
        parent_end, child_end = context.Pipe()
        process = context.Process(target=manager_main, args=(address, name, child_end))
        process.start()
        child_end.close()
        managers.append((process, parent_end))
        assert parent_end.poll(30), "the manager did not get ready"
        assert "ready" == parent_end.recv()
        return process

    fetched = FutureReply()
    try:
        member.serve(Served(registrar))
        first = manager()
        assert eventually(lambda: name in member.names(), timeout=10)
        os.kill(first.pid, signal.SIGKILL)
        assert eventually(lambda: name not in member.names(), timeout=10)  # heard to die
        hidden.set()
        manager()  # the restart: this process's presence does not hear of it
        os.kill(router_pid, signal.SIGSTOP)
        try:
            run_on_actor(
                registrar, lambda: DIRECTORY.lookup(name).tell(Fetch("s", registrar.name, fetched))
            )

            assert [] == registrar.client_queries(timeout=10)  # before the router runs
        finally:
            os.kill(router_pid, signal.SIGCONT)

        try:
            outcome: Any = fetched.future.get(timeout=40)
        except rr.RegistrarUnavailableError as exc:
            outcome = exc
        assert outcome == [] or isinstance(outcome, rr.RegistrarUnavailableError)
    finally:
        registrar.stop()
        member.close()
        for process, control in managers:
            with contextlib.suppress(OSError):
                control.send("stop")
            process.join(10)
            if process.is_alive():
                process.kill()
                process.join(5)
            control.close()
