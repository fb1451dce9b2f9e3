"""The carrier contract (`rr_actors._transport`: every `Messenger`), checked for every carrier.

Registrars talk across real processes: a call and its dedup, unloads, fetches and
statuses; notices that overtake the answer they are about; a peer that dies, stops,
freezes or answers what cannot be read. Each test runs once per carrier (`CARRIERS`).
`TestAtTheCarrier` drives a carrier itself, over the in-memory double too;
`TestLostForGood` is rule 19.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import os
import pickle
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import FutureReply, wait
from rr_actors._registrar.life import Served
from rr_actors._registrar.messages import Load, Revoke
from rr_actors._transport import System, Transport
from rr_actors.testing import MemoryNetwork, intercept
from tests.support import carriers
from tests.support.carriers import (
    BIG,
    CARRIERS,
    GATE,
    Children,
    ChildState,
    Provider,
    ProviderFactory,
    Recorder,
    _Gate,
    bytes_read,
    context,
    in_thread,
    load_count,
    own_provider_main,
    release_loads,
    setup_big,
    setup_servers,
    start_provider,
    unloads,
    wait_load_started,
)
from tests.support.hosts import free_port
from tests.support.waiting import wait_for

__all__ = ["context", "start_provider"]

# -- notices that overtake the answer they are about ---------------------------------------------
#
# The answer to a call comes back on the consumer's own connection to the provider, while the
# provider's notices (status, response update, revoke) travel on the provider's connection to
# the consumer's listener: another socket, read by another thread. A notice about a query
# whose answer the consumer has not recorded yet waits for that answer.


@pytest.fixture
def gate() -> Iterator[_Gate]:
    """A fresh `GATE`; released at the end so no reader thread stays held."""
    GATE.entered.clear()
    GATE.release.clear()
    yield GATE
    GATE.release.set()


class _Watched:
    """The consumer actor's handling of one kind of notice, and the answers it gave."""

    def __init__(self) -> None:
        self.handled = threading.Event()  # handled (or held) at least once
        self.answers: list[tuple[str, Any]] = []  # ("result", value) or ("error", error)

    def spy(self, reply: Any) -> Any:
        watched = self

        class Spy:
            def set_result(self, value: Any) -> None:
                watched.answers.append(("result", value))
                reply.set_result(value)

            def set_error(self, error: BaseException) -> None:
                watched.answers.append(("error", error))
                reply.set_error(error)

        return Spy()


def _watch(consumer: rr.ResourceRegistrar, step: str) -> _Watched:
    """Watch how the consumer's registrar actor handles one kind of notice and answers it."""
    watched = _Watched()
    spied: set[int] = set()

    def before(message: Any) -> None:
        reply = getattr(message, "reply", None)
        if reply is not None and id(message) not in spied:  # (a held one comes back)
            spied.add(id(message))
            object.__setattr__(message, "reply", watched.spy(reply))

    intercept(consumer, step, before=before, after=lambda _: watched.handled.set())
    return watched


def _in_thread(fn: Callable[[], Any]) -> tuple[list[Any], threading.Thread]:
    """Run `fn` on a thread; what it returned (or raised) lands in the list."""
    outcome: list[Any] = []

    def run() -> None:
        try:
            outcome.append(fn())
        except Exception as exc:
            outcome.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    return outcome, thread


def _first_query_id(registrar: rr.ResourceRegistrar) -> str:
    return registrar.server_queries("gated")[0].id


def _revoke_first_query(registrar: rr.ResourceRegistrar, consumer: str) -> None:
    """Tell `consumer` that the `gated` server's first query is revoked (as unregistering does)."""
    DIRECTORY.lookup(consumer).tell(Revoke((_first_query_id(registrar),)))


@dataclasses.dataclass
class _Overtaken:
    """What `overtake` saw: the call's outcome, and what the provider's function returned."""

    called: list[Any]
    done: list[Any]


Overtake = Callable[..., _Overtaken]


@pytest.fixture
def overtake(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    gate: _Gate,
    monkeypatch: pytest.MonkeyPatch,
) -> Overtake:
    """`overtake(step, fn, **call)`: a call to `gated` whose answer `fn`'s notice overtakes.

    The consumer calls a fresh provider's `gated` server; while the answer is held in this
    process, `fn(registrar)` runs in the provider's (on a thread: its own answer comes back
    on the held connection). The answer is released once the consumer's actor handled the
    `kind` notice `fn` sent (or held it).
    """

    def run(step: str, fn: Callable[[rr.ResourceRegistrar], Any], **call: Any) -> _Overtaken:
        provider = start_provider()
        watched = _watch(consumer, step)
        called, caller = _in_thread(lambda: consumer.call(provider.name, "gated", "r", **call))
        assert gate.entered.wait(10)  # the answer is being read, not yet recorded
        done, doer = _in_thread(lambda: system.run(provider.name, fn, timeout=20))
        assert watched.handled.wait(10)  # the notice reached the consumer's actor first
        gate.release.set()
        caller.join(10)
        doer.join(20)
        return _Overtaken(called, done)

    return run


def _send_status_to_first_query(system: System, provider: Provider) -> Any:
    return system.run(
        provider.name,
        lambda registrar: registrar.send_status(_first_query_id(registrar), rr.Status.ERROR, "x"),
        timeout=20,
    )


TIMEOUT = 5.0


"""Seconds the call below waits for its answer: what it waits for is held by a gate."""


class _EndHeld:
    """A registrar as a carrier serves it, whose end the carrier hears only once `heard`
    is set: it keeps delivering to a registrar that stopped (the window in which a
    peer's message races the stop, held open)."""

    def __init__(self, served: Served) -> None:
        self.served = served
        self.heard = threading.Event()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.served, name)

    def wait_ended(self, timeout: float | None = None) -> bool:
        return self.heard.wait(timeout) and self.served.wait_ended(timeout)


class _Lines(logging.Handler):
    """The `rr_actors` log lines about registrar `name`; `came` is set at the first."""

    def __init__(self, name: str) -> None:
        super().__init__(logging.DEBUG)
        self.name = name
        self.records: list[logging.LogRecord] = []
        self.came = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if self.name in record.getMessage():
            self.records.append(record)
            self.came.set()


def _tell_revoke(name: str, _registrar: rr.ResourceRegistrar) -> None:
    """Tell registrar `name` a `Revoke`: a message that wants no answer."""
    DIRECTORY.lookup(name).tell(Revoke(("q-1",)))


MIB = 1024 * 1024


# -- frozen peers (SIGSTOP) ---------------------------------------------------------------------


def fetch_big(provider: str) -> Callable[[rr.ResourceRegistrar], int]:
    """A function to run in a consumer process: call `provider/big`, return the size."""

    def fetch(registrar: rr.ResourceRegistrar) -> int:
        return len(registrar.call(provider, "big", "r", timeout=30).response)

    return fetch


def frozen_call(system: System) -> tuple[float, type[rr.RrError]]:
    """The timeout of a call to a frozen process, and the error it gets (carrier-neutral).

    A carrier with a `lease` (Zenoh) counts a process frozen longer than the lease as
    gone: `RegistrarUnavailableError`, well before a timeout longer than the lease. The
    AF_UNIX carrier has none: the call waits out its timeout (`CallTimeoutError`).
    """
    lease = getattr(system, "lease", None)
    if lease is None:
        return 1.0, rr.CallTimeoutError
    return 3 * lease + 2.0, rr.RegistrarUnavailableError


@dataclasses.dataclass
class Provided:
    """A provider registrar, wherever the carrier has it run."""

    name: str
    kill: Callable[[], None]
    stop: Callable[[], None]
    serve_again: Callable[[], None]
    """Serve a registrar of its name from another process (the test's; on the in-memory
    double, whose every `serve` is a process of its own, the same registrar again)."""


def _serve_as(system: Transport, name: str) -> None:
    """Start a registrar named `name` in this process and serve it on `system` (stopped
    after, served or not)."""
    with rr.ResourceRegistrar.start(name) as registrar:
        system.serve(Served(registrar))


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


LOST_WITHIN = 1.0


"""Seconds from a SIGKILL to `peer_lost` (the issue's bound)."""


# -- per carrier ----------------------------------------------------------------------------------


@dataclasses.dataclass
class Lab:
    """The test process's system on one carrier, and its provider processes."""

    carrier: str
    system: Transport
    join: tuple[Any, ...]
    children: Children
    endpoints: list[Recorder] = dataclasses.field(default_factory=list)

    def provider(self) -> tuple[str, multiprocessing.process.BaseProcess, Any]:
        """Start an unsupervised provider process; once other processes see it."""
        name = f"provider-{uuid.uuid4().hex[:8]}"
        process, parent_end = self.children.start(own_provider_main, self.join, name)
        assert wait_for(lambda: name in self.system.names(), 10.0), f"{name} not seen"
        self.connect(name)
        return name, process, parent_end

    def connect(self, name: str) -> None:
        """Reach registrar `name` once from this process (AF_UNIX: opens its connection)."""
        assert isinstance(self.system.run(name, id, timeout=10), int)

    def recorder(self) -> Recorder:
        """An endpoint served on the system in this process."""
        recorder = Recorder()
        self.system.serve(recorder)
        self.endpoints.append(recorder)
        return recorder

    def close(self) -> None:
        self.children.close()
        for recorder in self.endpoints:
            recorder.end()
        self.system.close()


def kill(process: multiprocessing.process.BaseProcess) -> float:
    """SIGKILL `process` (not reaped yet: its parent does that later); when it was sent."""
    assert process.pid
    killed_at = time.monotonic()
    os.kill(process.pid, signal.SIGKILL)
    return killed_at


# -- calls across processes ----------------------------------------------------------------------


def test_a_call_loads_once_and_an_equal_call_shares_the_resource(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()

    first = consumer.call(provider.name, "echo", {"cam": 1})
    second = consumer.call(provider.name, "echo", {"cam": 1})

    assert ({"resource": {"cam": 1}}, {"resource": {"cam": 1}}) == (
        first.response,
        second.response,
    )
    assert first.id != second.id
    assert 1 == system.run(provider.name, load_count, timeout=10)


def test_unload_across_processes_runs_the_unload_callback_after_the_last_consumer(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    first = consumer.call(provider.name, "echo", "r")
    second = consumer.call(provider.name, "echo", "r")

    consumer.unload(first.id)
    after_first = system.run(provider.name, unloads, timeout=10)
    consumer.unload(second.id)

    assert ([], ["r"]) == (after_first, system.run(provider.name, unloads, timeout=10))


def test_fetch_across_processes_lists_each_consumer_id_once(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    ids = {consumer.call(provider.name, "echo", "r").id for _ in range(3)}

    fetched = consumer.fetch_queries(provider.name, "echo")

    assert ids == {q.id for q in fetched}
    assert 3 == len(fetched)


def test_a_status_sent_in_the_provider_process_reaches_the_consumer_callback(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    heard: list[rr.StatusUpdate] = []
    query = consumer.call(provider.name, "echo", "r", on_status=lambda _q, u: heard.append(u))

    system.run(
        provider.name,
        lambda registrar: registrar.send_status(query.id, rr.Status.WARNING, "hot"),
        timeout=10,
    )

    assert [(query.id, rr.Status.WARNING, "hot")] == [
        (u.query_id, u.status, u.message) for u in heard
    ]


def test_a_status_that_overtakes_the_answer_to_its_call_still_reaches_the_callback(
    overtake: Overtake,
) -> None:
    heard: list[rr.StatusUpdate] = []

    seen = overtake(
        "status_notice",
        lambda registrar: registrar.send_status(
            _first_query_id(registrar), rr.Status.WARNING, "hot"
        ),
        on_status=lambda _q, u: heard.append(u),
    )

    [query] = seen.called
    assert [rr.StatusDelivery(reached=(query.id,), gave_up=())] == seen.done
    assert [(query.id, rr.Status.WARNING, "hot")] == [
        (u.query_id, u.status, u.message) for u in heard
    ]


def test_a_response_update_that_overtakes_the_answer_is_not_undone_by_it(
    overtake: Overtake, consumer: rr.ResourceRegistrar
) -> None:
    seen = overtake(
        "response_updated",
        lambda registrar: registrar.update_response(_first_query_id(registrar), "new"),
    )

    [query] = seen.called
    assert [None] == seen.done
    assert {query.id: "new"} == {q.id: q.response for q in consumer.client_queries()}


def test_a_revoke_that_overtakes_the_answer_leaves_no_client_record(
    overtake: Overtake, consumer: rr.ResourceRegistrar
) -> None:
    seen = overtake("revoke", functools.partial(_revoke_first_query, consumer=consumer.name))

    [query] = seen.called
    assert [None] == seen.done
    assert isinstance(query, rr.Query)
    assert [] == consumer.client_queries()


def test_a_status_waiting_for_an_answer_is_settled_when_the_call_times_out_instead(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    gate: _Gate,
    monkeypatch: pytest.MonkeyPatch,
    eventually: Callable[..., bool],
) -> None:
    provider = start_provider()
    watched = _watch(consumer, "status_notice")
    heard: list[rr.StatusUpdate] = []
    # The call must time out after its load started and the status was held: TIMEOUT
    # bounds those steps (0.5 s did not on a loaded machine: the call timed out before the
    # load started, or before the status was sent).
    called, caller = _in_thread(
        lambda: consumer.call(
            provider.name, "gated", "r", on_status=lambda _q, u: heard.append(u), timeout=TIMEOUT
        )
    )
    assert gate.entered.wait(TIMEOUT)
    sent, sender = _in_thread(lambda: _send_status_to_first_query(system, provider))
    assert watched.handled.wait(TIMEOUT)  # held: the answer is still being read
    assert not called  # (the call has not timed out yet)

    caller.join(TIMEOUT + 10)  # the call times out while its answer is held

    assert isinstance(called[0], rr.CallTimeoutError)
    assert eventually(lambda: [("result", ())] == watched.answers, timeout=8)  # none given up
    assert [] == heard
    gate.release.set()  # the late answer is given back
    sender.join(20)
    assert [()] == [delivery.gave_up for delivery in sent]
    assert eventually(lambda: [] == consumer.client_queries(), timeout=10)


def test_a_status_waiting_for_an_answer_is_answered_when_the_consumer_stops(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    gate: _Gate,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    provider = start_provider()
    watched = _watch(consumer, "status_notice")
    called, caller = _in_thread(lambda: consumer.call(provider.name, "gated", "r"))
    assert gate.entered.wait(10)
    sent, sender = _in_thread(lambda: _send_status_to_first_query(system, provider))
    assert watched.handled.wait(10)

    consumer.stop()

    [(kind, error)] = watched.answers
    assert ("error", rr.RegistrarStoppedError) == (kind, type(error))
    gate.release.set()
    caller.join(10)
    sender.join(20)
    assert [()] == [delivery.gave_up for delivery in sent]
    assert isinstance(called[0], rr.RegistrarStoppedError)


def test_run_reraises_what_the_function_raised_in_the_other_process(
    system: System, start_provider: ProviderFactory
) -> None:
    provider = start_provider()

    with pytest.raises(rr.UnknownQueryError):
        system.run(
            provider.name,
            lambda registrar: registrar.send_status("no-such-id", rr.Status.OK),
            timeout=10,
        )


# -- failures -------------------------------------------------------------------------------------


def test_a_call_in_flight_to_a_killed_process_fails_at_once_as_unavailable(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    done, outcome = in_thread(lambda: consumer.call(provider.name, "slow", "r", timeout=30))
    assert system.run(provider.name, wait_load_started, timeout=10)

    killed_at = time.monotonic()
    provider.kill()

    assert done.wait(10)
    assert isinstance(outcome.get("error"), rr.RegistrarUnavailableError)
    assert outcome["time"] - killed_at < 2.0  # far below the 30 s call timeout


@pytest.mark.parametrize(
    ("end", "error"), [("kill", rr.RegistrarUnavailableError), ("stop", rr.RegistrarStoppedError)]
)
def test_a_call_to_a_killed_process_fails_as_unavailable_to_a_cleanly_stopped_one_as_stopped(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory, end: str, error: type
) -> None:
    provider = start_provider()
    consumer.call(provider.name, "echo", "warm up the connection")
    getattr(provider, end)()

    with pytest.raises(error):
        consumer.call(provider.name, "echo", "r", timeout=10)


def test_a_message_for_a_registrar_stopped_meanwhile_is_dropped_in_one_line_saying_so(
    system: System, start_provider: ProviderFactory, caplog: pytest.LogCaptureFixture
) -> None:
    # Issue 40: a peer's message that wants no answer, reaching a registrar just stopped,
    # was logged at ERROR as "dropped a malformed message" with a RegistrarStoppedError
    # traceback.
    provider = start_provider()
    name = f"stopped-{uuid.uuid4().hex[:8]}"
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name))
    served = _EndHeld(Served(registrar))
    system.serve(served)
    lines = _Lines(name)
    log = logging.getLogger("rr_actors")
    caplog.set_level(logging.INFO, logger="rr_actors")
    registrar.stop()
    log.addHandler(lines)
    try:
        system.run(provider.name, functools.partial(_tell_revoke, name), timeout=10)
        assert lines.came.wait(10), "the message was never heard of"
    finally:
        log.removeHandler(lines)
        served.heard.set()

    assert [("INFO", None)] == [(r.levelname, r.exc_info) for r in lines.records]
    assert (
        f"dropped a Revoke message to registrar {name!r}: registrar {name!r} was stopped"
        == lines.records[0].getMessage()
    )


def test_a_call_to_a_name_nobody_serves_is_an_unknown_server(
    consumer: rr.ResourceRegistrar,
) -> None:
    with pytest.raises(rr.UnknownServerError):
        consumer.call(f"nobody-{uuid.uuid4().hex[:8]}", "echo", "r", timeout=10)


def test_a_restarted_provider_is_reached_again_on_the_next_call(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    consumer.call(provider.name, "echo", "before")
    provider.kill()
    with pytest.raises(rr.RegistrarUnavailableError):
        consumer.call(provider.name, "echo", "while dead", timeout=10)

    again = start_provider(name=provider.name)
    query = consumer.call(again.name, "echo", "after", timeout=10)

    assert {"resource": "after"} == query.response
    assert 1 == system.run(again.name, load_count, timeout=10)


def test_an_unpicklable_request_is_a_config_error_at_the_caller_and_nothing_loads(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()

    with pytest.raises(rr.ConfigError, match="not picklable") as caught:
        consumer.call(provider.name, "echo", threading.Lock(), timeout=10)

    assert f"'{provider.name}/echo'" in str(caught.value)
    assert isinstance(caught.value.__cause__, TypeError)
    assert 0 == system.run(provider.name, load_count, timeout=10)
    assert [] == consumer.client_queries()


@pytest.mark.parametrize(
    ("server", "error"),
    [("lock", "not picklable"), ("opaque", None)],
    ids=["an_unpicklable_response", "an_answer_that_cannot_be_unpickled_here"],
)
def test_a_response_not_picklable_there_or_not_unpicklable_here_releases_its_consumer_id(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    eventually: Callable[..., bool],
    server: str,
    error: str | None,
) -> None:
    provider = start_provider(setup_big)  # (`lock`: an unpicklable response; `opaque`: an
    # answer whose class this process cannot unpickle)
    with pytest.raises(rr.ResourceLoadError, match=error):
        consumer.call(provider.name, server, "r", timeout=10)

    assert eventually(lambda: ["r"] == system.run(provider.name, unloads, timeout=10))
    assert [] == system.run(
        provider.name, lambda registrar: registrar.server_queries(server), timeout=10
    )
    assert [] == consumer.client_queries()


def test_a_request_over_the_providers_max_message_bytes_fails_before_anything_is_sent(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider(max_message_bytes=MIB)
    consumer.call(provider.name, "echo", "warm up the connection", timeout=10)
    read_before = bytes_read(provider.pid)

    with pytest.raises(rr.MessageTooLargeError, match="nothing was sent") as caught:
        consumer.call(provider.name, "echo", b"x" * (2 * MIB), timeout=10)

    assert (True, MIB) == (isinstance(caught.value, rr.ConfigError), caught.value.limit)
    assert bytes_read(provider.pid) - read_before < MIB
    assert 1 == system.run(provider.name, load_count, timeout=10)  # (the warm-up)
    assert {"resource": "after"} == consumer.call(provider.name, "echo", "after").response


def test_a_response_over_the_providers_max_message_bytes_fails_the_call_and_releases_its_id(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    eventually: Callable[..., bool],
) -> None:
    provider = start_provider(max_message_bytes=MIB)

    with pytest.raises(rr.MessageTooLargeError, match="answer") as caught:
        consumer.call(provider.name, "sized", 2 * MIB, timeout=10)

    assert MIB == caught.value.limit
    assert eventually(lambda: [2 * MIB] == system.run(provider.name, unloads, timeout=10))
    assert [] == system.run(
        provider.name, lambda registrar: registrar.server_queries("sized"), timeout=10
    )
    assert [] == consumer.client_queries()


def test_no_raw_low_level_error_reaches_a_caller(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    held = consumer.call(provider.name, "echo", "held")
    done, outcome = in_thread(lambda: consumer.call(provider.name, "slow", "r", timeout=30))
    assert system.run(provider.name, wait_load_started, timeout=10)
    provider.kill()
    assert done.wait(10)
    errors: list[BaseException] = [outcome["error"]]
    attempts: list[Callable[[], Any]] = [
        lambda: consumer.call(provider.name, "echo", "r", timeout=10),
        lambda: consumer.unload(held.id, timeout=10),
        lambda: consumer.fetch_queries(provider.name, "echo", timeout=10),
        lambda: system.run(provider.name, load_count, timeout=10),
        lambda: consumer.call(provider.name, "echo", threading.Lock(), timeout=10),
    ]
    for attempt in attempts:
        try:
            attempt()
        except BaseException as exc:
            errors.append(exc)

    raw = (EOFError, BrokenPipeError, ConnectionResetError, pickle.PickleError)
    assert len(attempts) + 1 == len(errors)
    assert [] == [e for e in errors if isinstance(e, raw) or not isinstance(e, rr.RrError)]


@pytest.mark.parametrize("first", [False, True], ids=["a_call", "a_first_call"])
def test_a_call_to_a_frozen_process_fails_within_its_timeout(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory, first: bool
) -> None:
    timeout, expected = frozen_call(system)
    provider = start_provider(setup_big)
    if not first:  # (a connection, then a request too big for the socket's buffers)
        consumer.call(provider.name, "echo", "warm up the connection")
    request = "r" if first else b"x" * BIG
    os.kill(provider.pid, signal.SIGSTOP)
    try:
        done, outcome = in_thread(
            lambda: consumer.call(provider.name, "echo", request, timeout=timeout)
        )
        assert done.wait(10), "the call outlived its timeout"
    finally:
        provider.kill()

    assert isinstance(outcome.get("error"), expected)


def test_a_frozen_consumer_process_does_not_hold_up_its_provider(
    system: System, consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider(setup_big)
    frozen = start_provider()
    fetched, _ = in_thread(lambda: system.run(frozen.name, fetch_big(provider.name), timeout=30))
    assert system.run(provider.name, wait_load_started, timeout=10)
    os.kill(frozen.pid, signal.SIGSTOP)
    try:
        system.run(provider.name, release_loads, timeout=10)  # 20 MB go to the frozen one
        query = consumer.call(provider.name, "echo", "r", timeout=10)
    finally:
        frozen.kill()

    assert {"resource": "r"} == query.response
    assert fetched.wait(10)


# -- answers that cannot be read ------------------------------------------------------------------


def test_an_answer_that_cannot_be_unpickled_here_fails_the_call_as_a_load_error(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider(setup_big)

    with pytest.raises(rr.ResourceLoadError) as caught:
        consumer.call(provider.name, "opaque", "r", timeout=10)

    assert [(provider.name, "opaque", "RuntimeError")] == [
        (frame.registrar, frame.server, frame.exc_type) for frame in caught.value.stack
    ]


class TestAtTheCarrier:
    """The carrier contract at a carrier's own surface, over three carriers: AF_UNIX, Zenoh and
    the in-memory double (`rr_actors.testing.MemoryNetwork`): proof that a carrier is its link.

    The module's tests check the contract through registrars of different processes (a
    consumer's `call`, SIGKILL, SIGSTOP, a child's state). The in-memory double
    serves registrars of this one process, which find each other in the process's directory
    first, so those cases do not cross it: here the test sends through the carrier itself
    (`resolve(name).tell`, `run`), with the provider in a child process (AF_UNIX, Zenoh) or
    served on the double ("memory"), where a SIGKILL is `MemoryNetwork.cut`. Cases of the
    module's this covers: a call answered, the unload after it, `run` and what it
    raises, an unpicklable request, a request over `max_message_bytes`, an unpicklable
    answer and its compensation, a call in flight to a process killed, a call to a
    stopped one, an unknown name. Not here (they need processes of their own): a frozen
    process (SIGSTOP), notices that overtake an answer on another connection, raw
    low-level errors, an answer that cannot be unpickled in the caller's process.
    """

    @pytest.fixture(params=["memory", *sorted(CARRIERS)])
    def system(self, request: pytest.FixtureRequest) -> Iterator[Transport]:
        """A fresh system on each of the three carriers, closed after."""
        if request.param == "memory":
            created: Transport = MemoryNetwork(f"test-{uuid.uuid4().hex[:8]}")
        else:
            created = CARRIERS[request.param]()
        yield created
        created.close()

    @pytest.fixture
    def provider(
        self, system: Transport, request: pytest.FixtureRequest, context: object
    ) -> Iterator[Provided]:
        """A provider registrar with the servers of `setup_servers`: in a child process, or
        (memory) in this one, served on the double, with fresh `CHILD` records."""
        if not isinstance(system, MemoryNetwork):
            start: ProviderFactory = request.getfixturevalue("start_provider")
            child = start()
            yield Provided(
                child.name, child.kill, child.stop, functools.partial(_serve_as, system, child.name)
            )
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
        again = functools.partial(system.serve, Served(registrar))
        yield Provided(name, lambda: system.cut(name), registrar.stop, again)
        carriers.CHILD.release.set()
        registrar.stop()

    def test_a_load_told_through_the_carrier_is_answered_and_loads_once(
        self, system: Transport, provider: Provided
    ) -> None:
        load, reply = _load("echo", "r")

        assert {"resource": "r"} == _outcome(system, provider.name, load, reply)
        assert 1 == system.run(provider.name, load_count, timeout=10)

    def test_run_returns_what_the_function_returned_and_reraises_what_it_raised(
        self, system: Transport, provider: Provided
    ) -> None:
        def boom(_registrar: Any) -> None:
            raise KeyError("boom")

        assert provider.name == system.run(provider.name, lambda r: r.name, timeout=10)
        with pytest.raises(KeyError, match="boom"):
            system.run(provider.name, boom, timeout=10)
        assert [] == system.run(provider.name, unloads, timeout=10)

    def test_an_unpicklable_request_is_a_config_error_at_the_sender_and_nothing_loads(
        self, system: Transport, provider: Provided
    ) -> None:
        load, reply = _load("echo", threading.Lock())

        assert isinstance(_outcome(system, provider.name, load, reply), rr.ConfigError)
        assert 0 == system.run(provider.name, load_count, timeout=10)

    def test_a_request_over_max_message_bytes_is_refused_before_anything_is_sent(
        self, system: Transport, provider: Provided
    ) -> None:
        load, reply = _load("echo", b"x" * (carriers.PROVIDER_MAX_MESSAGE_BYTES + 1))

        assert isinstance(_outcome(system, provider.name, load, reply), rr.MessageTooLargeError)
        assert 0 == system.run(provider.name, load_count, timeout=10)

    def test_an_unpicklable_answer_fails_the_load_and_its_compensation_releases_the_id(
        self, system: Transport, provider: Provided, eventually: Callable[..., bool]
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
        self, system: Transport, provider: Provided
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
        self, system: Transport, provider: Provided, eventually: Callable[..., bool]
    ) -> None:
        provider.stop()
        load, reply = _load("echo", "r")

        assert eventually(
            lambda: isinstance(
                _outcome(system, provider.name, *_load("echo", "r")), rr.RegistrarStoppedError
            )
        )
        assert isinstance(_outcome(system, provider.name, load, reply), rr.RegistrarStoppedError)

    def test_a_name_another_process_serves_is_refused_and_the_first_serves_on(
        self, system: Transport, provider: Provided
    ) -> None:
        """One name, one registrar (rule 22): the simulated carrier's twin is
        `tests/simulation/test_network.py::test_a_second_server_of_a_name_served_on_its_side_is_refused_and_the_first_serves_on`."""
        with pytest.raises(rr.DuplicateNameError, match=provider.name):
            provider.serve_again()

        load, reply = _load("echo", "r")
        assert {"resource": "r"} == _outcome(system, provider.name, load, reply)
        assert 1 == system.run(provider.name, load_count, timeout=10)

    def test_run_on_a_name_nobody_serves_is_an_unknown_server(self, system: Transport) -> None:
        with pytest.raises(rr.UnknownServerError):
            system.run(f"nobody-{uuid.uuid4().hex[:8]}", len, timeout=10)


class TestLostForGood:
    """The carrier contract's rule 19, for every carrier: a provider gone for good is lost.

    A registrar of another process that is gone and that nobody will restart is *lost*: the
    carrier calls `Endpoint.peer_lost(name)` on every endpoint it serves in this process, and
    a real consumer registrar reports `FATAL` for the ids it held there (once) and forgets
    them. A provider whose supervisor lives on is not lost; nor is one stopped cleanly.

    Each test also kills an unsupervised provider as a control, so that "not lost" is not
    merely "the carrier never says lost". Real processes, real SIGKILLs; each test runs once
    per carrier (`CARRIERS`). An unsupervised provider is a process that joins the system
    by itself: on AF_UNIX it attaches the system's address; on Zenoh it is a router of its
    own that connects to the test's, or (`zenoh-attached`) a process that attaches through the
    test's router: only a manager process that router started counts as supervised by it.
    """

    pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")

    @pytest.fixture(params=[*sorted(CARRIERS), "zenoh-attached"])
    def lab(
        self, request: pytest.FixtureRequest, context: multiprocessing.context.ForkServerContext
    ) -> Iterator[Lab]:
        carrier = request.param
        if carrier == "unix":
            system = CARRIERS["unix"]()
            join: tuple[Any, ...] = ("attach", system.address)
        elif carrier == "zenoh":
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            name = f"lost-{uuid.uuid4().hex[:8]}"
            system = rr.ZenohNetwork(system=name, listen=[endpoint], tls=None)
            join = ("router", name, endpoint)
        elif carrier == "zenoh-attached":  # joins through the test's router, unsupervised
            system = CARRIERS["zenoh"]()
            join = ("attach", system.address)
        else:
            raise AssertionError(f"no unsupervised provider for carrier {carrier!r} yet")
        made = Lab(carrier, system, join, Children(context))
        yield made
        made.close()

    # -- the tests -----------------------------------------------------------------------------

    def test_a_killed_unsupervised_provider_is_lost_its_consumer_hears_fatal_once_and_forgets(
        self,
        lab: Lab,
    ) -> None:
        name, process, _ = lab.provider()
        recorder = lab.recorder()
        heard: list[tuple[str, rr.Status, str]] = []
        consumer = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=f"consumer-{uuid.uuid4().hex[:8]}", call_timeout=30.0),
            network=lab.system,
        )
        try:
            query = consumer.call(
                name,
                "echo",
                {"cam": 1},
                on_status=lambda q, u: heard.append((q.id, u.status, u.source)),
            )

            killed_at = kill(process)
            lost_at = recorder.wait_lost(name)

            assert lost_at is not None, f"{name} was never reported lost"
            assert lost_at - killed_at < LOST_WITHIN
            assert wait_for(lambda: bool(heard), 5.0)
            assert [] == [q for q in consumer.client_queries() if q.serving_rr == name]
            assert [(query.id, rr.Status.FATAL, f"{name}/echo")] == heard  # once
            with pytest.raises(rr.UnknownQueryError):
                consumer.unload(query.id, timeout=5)
            assert [name] == recorder.lost_names()
        finally:
            consumer.stop()

    def test_a_killed_manager_whose_supervisor_lives_is_not_lost(self, lab: Lab) -> None:
        manager = f"manager-{uuid.uuid4().hex[:8]}"
        sup = rr.Supervisor(
            [rr.ManagerSpec(manager, setup=None, isolation="process")], network=lab.system
        ).start()
        try:
            control, control_process, _ = lab.provider()
            recorder = lab.recorder()
            assert wait_for(lambda: manager in lab.system.names(), 10.0)
            lab.connect(manager)
            pid = sup.child(manager).pid
            assert pid

            os.kill(pid, signal.SIGKILL)
            kill(control_process)
            sup.wait_restarted(manager, timeout=15)
            assert recorder.wait_lost(control) is not None  # the carrier does say "lost"
            assert wait_for(lambda: manager in lab.system.names(), 10.0)
            os.kill(sup.child(manager).pid or 0, 0)  # (the restarted one runs)

            assert [control] == recorder.lost_names()
        finally:
            sup.stop()

    def test_a_provider_stopped_cleanly_is_not_lost(self, lab: Lab) -> None:
        stopped, stopped_process, stopped_control = lab.provider()
        control, control_process, _ = lab.provider()
        recorder = lab.recorder()
        consumer = rr.ResourceRegistrar.start(
            rr.RegistrarConfig(name=f"consumer-{uuid.uuid4().hex[:8]}", call_timeout=30.0),
            network=lab.system,
        )
        try:
            consumer.call(stopped, "echo", "r")  # connected, and holds an id there

            stopped_control.send("stop")
            stopped_process.join(10)
            assert 0 == stopped_process.exitcode
            kill(control_process)  # after the stop: its loss is reported after the stop's
            assert recorder.wait_lost(control) is not None

            assert [control] == recorder.lost_names()
        finally:
            consumer.stop()
