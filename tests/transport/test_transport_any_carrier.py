"""The carrier contract at a carrier's own surface, over three carriers: AF_UNIX, Zenoh and
the in-memory double (`rr_actors.testing.MemoryNetwork`): proof that a carrier is its link.

`test_transport_contract.py` checks the contract through registrars of different
processes (a consumer's `call`, SIGKILL, SIGSTOP, a child's state). The in-memory double
serves registrars of this one process, which find each other in the process's directory
first, so those cases do not cross it: here the test sends through the carrier itself
(`resolve(name).tell`, `run`), with the provider in a child process (AF_UNIX, Zenoh) or
served on the double ("memory"), where a SIGKILL is `MemoryNetwork.cut`. Cases of the
other file this covers: a call answered, the unload after it, `run` and what it
raises, an unpicklable request, a request over `max_message_bytes`, an unpicklable
answer and its compensation, a call in flight to a process killed, a call to a
stopped one, an unknown name. Not here (they need processes of their own): a frozen
process (SIGSTOP), notices that overtake an answer on another connection, raw
low-level errors, an answer that cannot be unpickled in the caller's process.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core.replies import FutureReply, wait
from rr_actors._transport import Transport
from rr_actors.testing import MemoryNetwork
from rr_actors.testing.carrier import Load, Served
from tests.support import carriers
from tests.support.carriers import (
    CARRIERS,
    ChildState,
    ProviderFactory,
    context,
    load_count,
    setup_servers,
    start_provider,
    unloads,
    wait_load_started,
)

__all__ = ["context", "start_provider"]  # (fixtures: the child processes of AF_UNIX, Zenoh)


@pytest.fixture(params=["memory", *sorted(CARRIERS)])
def system(request: pytest.FixtureRequest) -> Iterator[Transport]:
    """A fresh system on each of the three carriers, closed after."""
    if request.param == "memory":
        created: Transport = MemoryNetwork(f"test-{uuid.uuid4().hex[:8]}")
    else:
        created = CARRIERS[request.param]()
    yield created
    created.close()


@dataclasses.dataclass
class Provided:
    """A provider registrar, wherever the carrier has it run."""

    name: str
    kill: Callable[[], None]
    stop: Callable[[], None]


@pytest.fixture
def provider(
    system: Transport, request: pytest.FixtureRequest, context: object
) -> Iterator[Provided]:
    """A provider registrar with the servers of `setup_servers`: in a child process, or
    (memory) in this one, served on the double, with fresh `CHILD` records."""
    if not isinstance(system, MemoryNetwork):
        start: ProviderFactory = request.getfixturevalue("start_provider")
        child = start()
        yield Provided(child.name, child.kill, child.stop)
        return
    carriers.CHILD.__init__()  # type: ignore[misc]  # (fresh records, this process's)
    assert isinstance(carriers.CHILD, ChildState)
    name = f"provider-{uuid.uuid4().hex[:8]}"
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(
            name=name, call_timeout=10.0, max_message_bytes=carriers.PROVIDER_MAX_MESSAGE_BYTES
        )
    )
    setup_servers(registrar)
    system.serve(Served(registrar))
    yield Provided(name, lambda: system.cut(name), registrar.stop)
    carriers.CHILD.release.set()
    registrar.stop()


def _load(server: str, request: Any) -> tuple[Load, FutureReply]:
    reply = FutureReply()
    return Load(f"q-{uuid.uuid4().hex[:8]}", server, request, "tester", (), reply), reply


def _outcome(system: Transport, name: str, message: Load, reply: FutureReply) -> Any:
    """Tell `message` through the carrier; what its reply got (or what `tell` raised)."""
    peer = system.resolve(name)
    assert peer is not None
    try:
        peer.tell(message)
    except rr.RrError as exc:
        return exc
    return _answer(reply)


def _answer(reply: FutureReply) -> Any:
    """The value or the error `reply` got (at most 10 s)."""
    try:
        return wait(reply.future, 10, "the test's load")
    except rr.RrError as exc:
        return exc


def test_a_load_told_through_the_carrier_is_answered_and_loads_once(
    system: Transport, provider: Provided
) -> None:
    load, reply = _load("echo", "r")

    assert {"resource": "r"} == _outcome(system, provider.name, load, reply)
    assert 1 == system.run(provider.name, load_count, timeout=10)


def test_run_returns_what_the_function_returned_and_reraises_what_it_raised(
    system: Transport, provider: Provided
) -> None:
    def boom(_registrar: Any) -> None:
        raise KeyError("boom")

    assert provider.name == system.run(provider.name, lambda r: r.name, timeout=10)
    with pytest.raises(KeyError, match="boom"):
        system.run(provider.name, boom, timeout=10)
    assert [] == system.run(provider.name, unloads, timeout=10)


def test_an_unpicklable_request_is_a_config_error_at_the_sender_and_nothing_loads(
    system: Transport, provider: Provided
) -> None:
    load, reply = _load("echo", threading.Lock())

    assert isinstance(_outcome(system, provider.name, load, reply), rr.ConfigError)
    assert 0 == system.run(provider.name, load_count, timeout=10)


def test_a_request_over_max_message_bytes_is_refused_before_anything_is_sent(
    system: Transport, provider: Provided
) -> None:
    load, reply = _load("echo", b"x" * (carriers.PROVIDER_MAX_MESSAGE_BYTES + 1))

    assert isinstance(_outcome(system, provider.name, load, reply), rr.MessageTooLargeError)
    assert 0 == system.run(provider.name, load_count, timeout=10)


def test_an_unpicklable_answer_fails_the_load_and_its_compensation_releases_the_id(
    system: Transport, provider: Provided, eventually: Callable[..., bool]
) -> None:
    load, reply = _load("lock", "r")

    error = _outcome(system, provider.name, load, reply)

    assert isinstance(error, rr.ResourceLoadError), error
    assert "not picklable" in str(error)
    assert eventually(lambda: ["r"] == system.run(provider.name, unloads, timeout=10))
    assert [] == system.run(
        provider.name, lambda registrar: registrar.server_queries("lock"), timeout=10
    )


def test_a_reply_waiting_on_a_killed_process_fails_at_once_as_unavailable(
    system: Transport, provider: Provided
) -> None:
    load, reply = _load("slow", "r")
    peer = system.resolve(provider.name)
    assert peer is not None
    peer.tell(load)
    assert system.run(provider.name, wait_load_started, timeout=10)

    killed_at = time.monotonic()
    provider.kill()

    error = _answer(reply)
    assert isinstance(error, rr.RegistrarUnavailableError)
    assert time.monotonic() - killed_at < 5.0  # far below any call timeout
    later, later_reply = _load("echo", "r")
    assert isinstance(_outcome(system, provider.name, later, later_reply), rr.RrError)


def test_a_load_to_a_cleanly_stopped_registrar_fails_as_stopped(
    system: Transport, provider: Provided, eventually: Callable[..., bool]
) -> None:
    provider.stop()
    load, reply = _load("echo", "r")

    assert eventually(
        lambda: isinstance(
            _outcome(system, provider.name, *_load("echo", "r")), rr.RegistrarStoppedError
        )
    )
    assert isinstance(_outcome(system, provider.name, load, reply), rr.RegistrarStoppedError)


def test_run_on_a_name_nobody_serves_is_an_unknown_server(system: Transport) -> None:
    with pytest.raises(rr.UnknownServerError):
        system.run(f"nobody-{uuid.uuid4().hex[:8]}", len, timeout=10)
