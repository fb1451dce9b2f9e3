"""Registrars talking across real processes over the system's authenticated channels.

Each provider registrar runs in a child process started with the "forkserver" context: the
child attaches the system, starts a registrar, runs a setup function (cloudpickled),
serves the registrar, says "ready" over a pipe and waits until the pipe says "stop" (or
closes: a child never outlives the test process). The consumer is in the test process.

Functions that read a child's state (`load_count`, `wait_load_started`, ...) are module
level, so cloudpickle sends them by reference and they run against the child's globals.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import multiprocessing.synchronize
import os
import pickle
import signal
import socket
import stat
import struct
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._core.directory import DIRECTORY
from rr_actors._registrar.messages import Fetch, Load, Revoke
from rr_actors._transport.unix import (
    RemotePeer,
    System,
    _Channel,
    _frame,
    _frames,
    _Writer,
    attach,
)
from rr_actors.testing import intercept

Setup = Callable[[rr.ResourceRegistrar], None]

# -- what runs in the child -------------------------------------------------------------------


@dataclasses.dataclass
class ChildState:
    """Per-process record of what the provider's callbacks did (lives in the child)."""

    loads: list[Any] = dataclasses.field(default_factory=list)
    unloads: list[Any] = dataclasses.field(default_factory=list)
    load_started: threading.Event = dataclasses.field(default_factory=threading.Event)
    release: threading.Event = dataclasses.field(default_factory=threading.Event)
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)
    warnings: list[str] = dataclasses.field(default_factory=list)


CHILD = ChildState()


def _record_load(request: Any) -> Any:
    with CHILD.lock:
        CHILD.loads.append(request)
    return {"resource": request}


def _record_unload(request: Any, _response: Any) -> None:
    with CHILD.lock:
        CHILD.unloads.append(request)


def _blocking_load(request: Any) -> Any:
    CHILD.load_started.set()
    CHILD.release.wait(30)
    return request


class _Gate:
    """Holds this process's reader thread while it unpickles a `Gated` answer."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()


GATE = _Gate()  # the test process's (the consumer's); reset by the `gate` fixture


def _rebuild_gated(value: Any) -> Any:
    GATE.entered.set()
    GATE.release.wait(30)
    return value


class Gated:
    """A response whose unpickling waits until `GATE.release` is set (it unpickles as `value`)."""

    def __init__(self, value: Any) -> None:
        self.value = value

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild_gated, (self.value,))


def _gated_load(request: Any) -> Any:
    return Gated(request)


def setup_servers(registrar: rr.ResourceRegistrar) -> None:
    """The provider's servers: a recording `echo`, a `slow` one and one with a bad response."""
    registrar.register_server("echo", load=_record_load, unload=_record_unload)
    registrar.register_server("gated", load=_gated_load, unload=_record_unload)
    registrar.register_server("slow", load=_blocking_load, unload=_record_unload)
    registrar.register_server("lock", load=lambda _request: threading.Lock(), unload=_record_unload)


def load_count(_registrar: rr.ResourceRegistrar) -> int:
    """How many times a `load` callback ran in this (child) process."""
    return len(CHILD.loads)


def unloads(_registrar: rr.ResourceRegistrar) -> list[Any]:
    """The requests whose `unload` callback ran in this (child) process."""
    return list(CHILD.unloads)


def wait_load_started(_registrar: rr.ResourceRegistrar) -> bool:
    """Block (bounded) until the `slow` server's load runs in this process."""
    return CHILD.load_started.wait(10)


BIG = 20_000_000  # bytes: far more than a socket buffer holds


def _big_load(_request: Any) -> Any:
    CHILD.load_started.set()
    CHILD.release.wait(30)
    return b"x" * BIG


def _refuse_rebuild() -> None:
    raise RuntimeError("cannot be rebuilt here")


class Opaque:
    """Pickles fine; unpickling it (in the consumer) raises."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (_refuse_rebuild, ())


def setup_big(registrar: rr.ResourceRegistrar) -> None:
    """`big` answers 20 MB once released; `echo` records; `opaque` answers an `Opaque`."""
    setup_servers(registrar)
    registrar.register_server("big", load=_big_load, unload=_record_unload)
    registrar.register_server("opaque", load=lambda _request: Opaque(), unload=_record_unload)


def release_loads(_registrar: rr.ResourceRegistrar) -> None:
    """Let blocked `slow` / `big` loads of this (child) process return."""
    CHILD.release.set()


class _WarningLog(logging.Handler):
    def emit(self, record: logging.LogRecord) -> None:
        with CHILD.lock:
            CHILD.warnings.append(record.getMessage())


def record_warnings(_registrar: rr.ResourceRegistrar) -> None:
    """From now on, keep what the `rr_actors` logger says at WARNING and above here."""
    handler = _WarningLog(logging.WARNING)
    logging.getLogger("rr_actors").addHandler(handler)


def warnings_logged(_registrar: rr.ResourceRegistrar) -> list[str]:
    """The warnings recorded in this (child) process."""
    with CHILD.lock:
        return list(CHILD.warnings)


def provider_main(
    address: Any, name: str, setup: bytes, control: multiprocessing.connection.Connection
) -> None:
    """A provider process: serve a registrar until told to stop (or the parent is gone)."""
    attached = attach(address)
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, call_timeout=10.0))
    try:
        cloudpickle.loads(setup)(registrar)
        attached.serve(registrar)
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        CHILD.release.set()
        registrar.stop()
        attached.close()


# -- fixtures -----------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def context() -> multiprocessing.context.ForkServerContext:
    """The forkserver context, with its helper processes started before any leak check."""
    ctx = multiprocessing.get_context("forkserver")
    assert isinstance(ctx, multiprocessing.context.ForkServerContext)
    ctx.set_forkserver_preload(["rr_actors", "rr_actors._transport.unix", "cloudpickle"])
    multiprocessing.forkserver.ensure_running()
    return ctx


@pytest.fixture
def system() -> Iterator[System]:
    """A fresh system (runtime directory + authkey), closed after the test."""
    created = System.create()
    yield created
    created.close()


@pytest.fixture
def consumer(system: System) -> Iterator[rr.ResourceRegistrar]:
    """A consumer registrar in the test process, served on the system."""
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"consumer-{uuid.uuid4().hex[:8]}", call_timeout=30.0)
    )
    system.serve(registrar)
    yield registrar
    registrar.stop()


@dataclasses.dataclass
class Provider:
    """A provider registrar's child process, as the test sees it."""

    name: str
    process: multiprocessing.process.BaseProcess
    control: multiprocessing.connection.Connection

    @property
    def pid(self) -> int:
        assert self.process.pid is not None
        return self.process.pid

    def kill(self) -> None:
        """SIGKILL the process and reap it."""
        os.kill(self.pid, signal.SIGKILL)
        self.process.join(10)
        assert not self.process.is_alive()

    def stop(self) -> None:
        """Ask for a clean stop (registrar.stop(), then exit) and reap the process."""
        with contextlib.suppress(OSError):
            self.control.send("stop")
        self.process.join(10)
        assert 0 == self.process.exitcode


ProviderFactory = Callable[..., Provider]


@pytest.fixture
def start_provider(
    context: multiprocessing.context.ForkServerContext, system: System
) -> Iterator[ProviderFactory]:
    """Start provider processes: `start_provider(setup, name=None)`; all are reaped after."""
    started: list[Provider] = []

    def start(setup: Setup = setup_servers, name: str | None = None) -> Provider:
        name = name or f"provider-{uuid.uuid4().hex[:8]}"
        parent_end, child_end = context.Pipe()
        process = context.Process(
            target=provider_main,
            args=(system.address, name, cloudpickle.dumps(setup), child_end),
            name=name,
            daemon=True,
        )
        process.start()
        child_end.close()
        provider = Provider(name, process, parent_end)
        started.append(provider)
        assert parent_end.poll(30), "the provider process did not get ready"
        assert "ready" == parent_end.recv()
        return provider

    yield start
    for provider in started:
        with contextlib.suppress(OSError):
            provider.control.send("stop")
    for provider in started:
        provider.process.join(10)
        if provider.process.is_alive():
            provider.process.kill()
            provider.process.join(5)
        provider.control.close()


def in_thread(fn: Callable[[], Any]) -> tuple[threading.Event, dict[str, Any]]:
    """Run `fn` on a thread; the dict gets `result` or `error` and the `time` it ended."""
    done = threading.Event()
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["result"] = fn()
        except BaseException as exc:
            outcome["error"] = exc
        outcome["time"] = time.monotonic()
        done.set()

    threading.Thread(target=run, daemon=True).start()
    return done, outcome


# -- the system ---------------------------------------------------------------------------------


def test_the_runtime_directory_is_private_to_its_user(system: System) -> None:
    assert 0o700 == stat.S_IMODE(os.stat(system.address.runtime_dir).st_mode)


def test_a_given_runtime_directory_is_made_private(tmp_path: Path) -> None:
    wanted = tmp_path / "run"
    wanted.mkdir(mode=0o755)
    created = System.create(str(wanted))
    try:
        assert 0o700 == stat.S_IMODE(os.stat(wanted).st_mode)
    finally:
        created.close()


def test_closing_a_system_keeps_a_given_directory_and_the_files_it_did_not_make(
    tmp_path: Path,
) -> None:
    wanted = tmp_path / "run"
    wanted.mkdir()
    (wanted / "notes.txt").write_text("mine")
    created = System.create(str(wanted))
    registrar = rr.ResourceRegistrar.start(f"kept-{uuid.uuid4().hex[:8]}")
    try:
        created.serve(registrar)
    finally:
        registrar.stop()
        created.close()

    assert ["notes.txt"] == sorted(os.listdir(wanted))


def test_closing_a_system_removes_the_runtime_directory_it_made(tmp_path: Path) -> None:
    wanted = tmp_path / "made" / "run"
    created = System.create(str(wanted))
    registrar = rr.ResourceRegistrar.start(f"made-{uuid.uuid4().hex[:8]}")
    try:
        created.serve(registrar)
    finally:
        registrar.stop()
        created.close()

    assert not wanted.exists()


def test_the_system_address_pickles_and_hides_its_key_in_its_repr(system: System) -> None:
    address = pickle.loads(pickle.dumps(system.address))

    assert system.address == address
    assert system.address.authkey.hex() not in repr(address)


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
    assert [None] == seen.done
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


def _send_status_to_first_query(system: System, provider: Provider) -> Any:
    return system.run(
        provider.name,
        lambda registrar: registrar.send_status(_first_query_id(registrar), rr.Status.ERROR, "x"),
        timeout=20,
    )


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
    called, caller = _in_thread(
        lambda: consumer.call(
            provider.name, "gated", "r", on_status=lambda _q, u: heard.append(u), timeout=0.5
        )
    )
    assert gate.entered.wait(10)
    sent, sender = _in_thread(lambda: _send_status_to_first_query(system, provider))
    assert watched.handled.wait(10)  # held: the answer is still being read

    caller.join(10)  # the call times out while its answer is held

    assert isinstance(called[0], rr.CallTimeoutError)
    assert eventually(lambda: [("result", None)] == watched.answers, timeout=8)
    assert [] == heard
    gate.release.set()  # the late answer is given back
    sender.join(20)
    assert [None] == sent
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
    assert [None] == sent
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


def test_a_call_to_a_killed_process_fails_as_unavailable(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    consumer.call(provider.name, "echo", "warm up the connection")
    provider.kill()

    with pytest.raises(rr.RegistrarUnavailableError):
        consumer.call(provider.name, "echo", "r", timeout=10)


def test_a_call_to_a_cleanly_stopped_process_fails_as_stopped(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    consumer.call(provider.name, "echo", "warm up the connection")
    provider.stop()

    with pytest.raises(rr.RegistrarStoppedError):
        consumer.call(provider.name, "echo", "r", timeout=10)


class _SlowShutdown:
    """A listening socket whose `shutdown` waits for `release` (to hold a close mid-way)."""

    def __init__(self, sock: socket.socket, entered: threading.Event, release: threading.Event):
        self.sock, self.entered, self.release = sock, entered, release

    def shutdown(self, how: int) -> None:
        self.entered.set()
        self.release.wait(10)
        self.sock.shutdown(how)

    def close(self) -> None:
        self.sock.close()


def test_a_second_close_of_a_listener_returns_only_once_the_first_finished(
    system: System, consumer: rr.ResourceRegistrar
) -> None:
    # The registrar's watcher and the system's close() may both close its listener; a
    # process that exits after its own close() must not leave the socket half closed
    # (the watcher is a daemon thread: the exit cuts it short).
    listener = system._listeners[consumer.name]
    entered, release, second_done = threading.Event(), threading.Event(), threading.Event()
    listener._sock = _SlowShutdown(listener._sock, entered, release)  # type: ignore[assignment]

    def second() -> None:
        listener.close(stopped=True)
        second_done.set()

    first_thread = threading.Thread(target=listener.close, kwargs={"stopped": True})
    second_thread = threading.Thread(target=second)
    try:
        first_thread.start()
        assert entered.wait(10)
        second_thread.start()
        assert not second_done.wait(0.3), "returned while the first close was half way"
    finally:
        release.set()
        first_thread.join(10)
        second_thread.join(10)

    assert second_done.is_set()
    assert (True, False) == (os.path.exists(listener.tombstone), os.path.exists(listener.path))


def test_closing_the_system_waits_for_a_stopped_registrar_s_listener_to_close(
    system: System,
) -> None:
    # The registrar's watcher thread closes its listener when the registrar stops, while
    # the process may already be in `close()` of its system, on its way out.
    registrar = rr.ResourceRegistrar.start(f"closing-{uuid.uuid4().hex[:8]}")
    system.serve(registrar)
    listener = system._listeners[registrar.name]
    entered, release, closed = threading.Event(), threading.Event(), threading.Event()
    listener._sock = _SlowShutdown(listener._sock, entered, release)  # type: ignore[assignment]

    def close_system() -> None:
        system.close()
        closed.set()

    closing = threading.Thread(target=close_system)
    try:
        registrar.stop()  # the watcher starts closing the listener, and is held half way
        assert entered.wait(10)
        closing.start()
        assert not closed.wait(0.3), "the system closed while the listener was half closed"
    finally:
        release.set()
        closing.join(10)

    assert closed.is_set()
    assert not os.path.exists(listener.path)  # (the system's close removed the tombstone)


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


def test_an_unpicklable_response_fails_the_call_and_releases_its_consumer_id(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    eventually: Callable[..., bool],
) -> None:
    provider = start_provider()

    with pytest.raises(rr.ResourceLoadError, match="not picklable"):
        consumer.call(provider.name, "lock", "r", timeout=10)

    assert eventually(lambda: ["r"] == system.run(provider.name, unloads, timeout=10))
    assert [] == system.run(
        provider.name, lambda registrar: registrar.server_queries("lock"), timeout=10
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


# -- authentication --------------------------------------------------------------------------------


class _Marker:
    """A payload whose unpickling would create a file (to show nothing was unpickled)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (Path(self.path),))


def _drain_until_closed(conn: multiprocessing.connection.Connection) -> bool:
    """Read until the other side closes the connection; False if it stays open for 10 s."""
    while True:
        try:
            if not conn.poll(10):
                return False
            conn.recv_bytes()
        except (EOFError, OSError):
            return True


def _evil_load(name: str, marker: str) -> bytes:
    message = Load("q-1", "echo", _Marker(marker), "intruder", (), None)  # type: ignore[arg-type]
    payload: bytes = cloudpickle.dumps(message)
    return b"\x00" * 8 + payload


def test_a_client_with_the_wrong_authkey_is_refused_and_nothing_runs(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
) -> None:
    provider = start_provider()
    path = system.address.socket_path(provider.name)

    with pytest.raises(multiprocessing.AuthenticationError):
        multiprocessing.connection.Client(path, family="AF_UNIX", authkey=os.urandom(32))

    assert 0 == system.run(provider.name, load_count, timeout=10)
    assert {"resource": "ok"} == consumer.call(provider.name, "echo", "ok").response


def test_a_client_without_an_authkey_is_refused_before_its_payload_is_unpickled(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    tmp_path: Path,
) -> None:
    provider = start_provider()
    marker = tmp_path / "unpickled"
    conn = multiprocessing.connection.Client(
        system.address.socket_path(provider.name), family="AF_UNIX"
    )
    try:
        for _ in range(3):
            conn.send_bytes(_evil_load(provider.name, str(marker)))
        assert _drain_until_closed(conn), "the listener kept an unauthenticated connection"
    finally:
        conn.close()

    assert not marker.exists()
    assert 0 == system.run(provider.name, load_count, timeout=10)
    assert {"resource": "ok"} == consumer.call(provider.name, "echo", "ok").response


def test_a_stalled_unauthenticated_client_does_not_block_others(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory, system: System
) -> None:
    provider = start_provider()
    silent = multiprocessing.connection.Client(
        system.address.socket_path(provider.name), family="AF_UNIX"
    )
    try:
        query = consumer.call(provider.name, "echo", "ok", timeout=10)
    finally:
        silent.close()

    assert {"resource": "ok"} == query.response


def test_a_remote_peer_is_what_the_directory_hands_out_for_another_process(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider()

    assert isinstance(DIRECTORY.lookup(provider.name), RemotePeer)
    assert not isinstance(DIRECTORY.lookup(consumer.name), RemotePeer)


# -- frozen peers (SIGSTOP) ---------------------------------------------------------------------


def fetch_big(provider: str) -> Callable[[rr.ResourceRegistrar], int]:
    """A function to run in a consumer process: call `provider/big`, return the size."""

    def fetch(registrar: rr.ResourceRegistrar) -> int:
        return len(registrar.call(provider, "big", "r", timeout=30).response)

    return fetch


def test_a_call_to_a_frozen_process_fails_within_its_timeout(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider(setup_big)
    consumer.call(provider.name, "echo", "warm up the connection")
    os.kill(provider.pid, signal.SIGSTOP)
    try:
        done, outcome = in_thread(
            lambda: consumer.call(provider.name, "echo", b"x" * BIG, timeout=1.0)
        )
        assert done.wait(10), "the call outlived its timeout"
    finally:
        provider.kill()

    assert isinstance(outcome.get("error"), rr.CallTimeoutError)


def test_a_first_call_to_a_frozen_process_fails_within_its_timeout(
    consumer: rr.ResourceRegistrar, start_provider: ProviderFactory
) -> None:
    provider = start_provider(setup_big)
    os.kill(provider.pid, signal.SIGSTOP)
    try:
        done, outcome = in_thread(lambda: consumer.call(provider.name, "echo", "r", timeout=1.0))
        assert done.wait(10), "the call outlived its timeout"
    finally:
        provider.kill()

    assert isinstance(outcome.get("error"), rr.CallTimeoutError)


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


def test_an_answer_that_cannot_be_unpickled_here_releases_its_consumer_id(
    system: System,
    consumer: rr.ResourceRegistrar,
    start_provider: ProviderFactory,
    eventually: Callable[..., bool],
) -> None:
    provider = start_provider(setup_big)
    with pytest.raises(rr.ResourceLoadError):
        consumer.call(provider.name, "opaque", "r", timeout=10)

    assert eventually(lambda: ["r"] == system.run(provider.name, unloads, timeout=10))
    assert [] == system.run(
        provider.name, lambda registrar: registrar.server_queries("opaque"), timeout=10
    )
    assert [] == consumer.client_queries()


# -- malformed frames from an authenticated peer -------------------------------------------------


def _raw_client(system: System, name: str) -> multiprocessing.connection.Connection:
    """A connection to registrar `name` that passed the handshake (it knows the authkey)."""
    return multiprocessing.connection.Client(
        system.address.socket_path(name), family="AF_UNIX", authkey=system.address.authkey
    )


def _answer_to(conn: multiprocessing.connection.Connection, token: int) -> Any:
    """The next answer on `conn` (bounded wait), which must carry `token`."""
    assert conn.poll(10), "no answer came"
    data = conn.recv_bytes()
    assert token == struct.unpack_from("<Q", data)[0]
    return pickle.loads(data[8:])


def test_a_short_frame_from_an_authenticated_peer_leaves_its_connection_serving(
    system: System, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    conn = _raw_client(system, provider.name)
    try:
        conn.send_bytes(b"\x01\x02")
        fetch = Fetch("echo", "intruder", None)  # type: ignore[arg-type]
        conn.send_bytes(struct.pack("<Q", 7) + cloudpickle.dumps(fetch))
        answer = _answer_to(conn, 7)
    finally:
        conn.close()

    assert ([], None) == answer


def test_a_message_without_a_reply_field_is_answered_with_an_error(
    system: System, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    conn = _raw_client(system, provider.name)
    try:
        conn.send_bytes(struct.pack("<Q", 9) + pickle.dumps(42))
        _value, error = _answer_to(conn, 9)
    finally:
        conn.close()

    assert isinstance(error, rr.RrError)


def _fake_provider(listening: socket.socket, authkey: bytes) -> None:
    """Accept one connection; before the first answer send a short frame, answer the rest."""
    try:
        accepted, _ = listening.accept()
    except OSError:
        return
    accepted.settimeout(None)
    conn = multiprocessing.connection.Connection(accepted.detach())
    with contextlib.suppress(EOFError, OSError):
        multiprocessing.connection.deliver_challenge(conn, authkey)
        multiprocessing.connection.answer_challenge(conn, authkey)
        value: Any = "from the fake"
        while True:
            (token,) = struct.unpack_from("<Q", conn.recv_bytes())
            if value is not None:
                conn.send_bytes(b"\x01")
            if token:
                conn.send_bytes(struct.pack("<Q", token) + pickle.dumps((value, None)))
            value = None
    conn.close()


def test_a_malformed_answer_does_not_stop_the_reader_of_its_connection(
    system: System, consumer: rr.ResourceRegistrar
) -> None:
    name = f"fake-{uuid.uuid4().hex[:8]}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listening:
        listening.bind(system.address.socket_path(name))
        listening.listen(1)
        listening.settimeout(10)
        threading.Thread(
            target=_fake_provider, args=(listening, system.address.authkey), daemon=True
        ).start()
        query = consumer.call(name, "echo", "r", timeout=10)

    assert "from the fake" == query.response


# -- one owner per name ---------------------------------------------------------------------------


def contender_main(
    address: Any,
    names: list[str],
    barrier: multiprocessing.synchronize.Barrier,
    control: multiprocessing.connection.Connection,
) -> None:
    """For each name: serve it when all contenders are ready, report, unserve on "next"."""
    attached = attach(address)
    try:
        for name in names:
            registrar = rr.ResourceRegistrar.start(name)
            try:
                outcome = "served"
                barrier.wait(30)
                try:
                    attached.serve(registrar)
                except rr.RrError as exc:
                    outcome = type(exc).__name__
                control.send(outcome)
                if control.recv() != "next":
                    return
            finally:
                registrar.stop()
    except (EOFError, OSError, threading.BrokenBarrierError):
        return
    finally:
        attached.close()


def test_of_processes_racing_to_serve_one_name_exactly_one_serves_it(
    system: System, context: multiprocessing.context.ForkServerContext
) -> None:
    rounds, parties = 10, 4
    names = [f"contested-{number}-{uuid.uuid4().hex[:8]}" for number in range(rounds)]
    for name in names:  # each name starts with a socket left behind by a dead process
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as stale:
            stale.bind(system.address.socket_path(name))
    barrier = context.Barrier(parties)
    contenders = []
    for _ in range(parties):
        parent_end, child_end = context.Pipe()
        process = context.Process(
            target=contender_main, args=(system.address, names, barrier, child_end), daemon=True
        )
        process.start()
        child_end.close()
        contenders.append((process, parent_end))
    outcomes = []
    try:
        for _ in names:
            outcome = []
            for _process, control in contenders:
                assert control.poll(30), "a contender did not report"
                outcome.append(control.recv())
            outcomes.append(sorted(outcome))
            for _process, control in contenders:
                control.send("next")
    finally:
        for process, control in contenders:
            control.close()
            process.join(10)

    assert [["DuplicateNameError"] * (parties - 1) + ["served"]] * rounds == outcomes


def test_a_refused_duplicate_does_not_make_the_owner_log_a_warning(
    system: System, start_provider: ProviderFactory
) -> None:
    provider = start_provider()
    system.run(provider.name, record_warnings, timeout=10)
    duplicate = rr.ResourceRegistrar.start(provider.name)
    try:
        with pytest.raises(rr.DuplicateNameError):
            system.serve(duplicate)
    finally:
        duplicate.stop()

    assert [] == system.run(provider.name, warnings_logged, timeout=10)


# -- internals -----------------------------------------------------------------------------------


class _CountingReply:
    """A reply that counts how often it was answered."""

    __slots__ = ("answers",)

    def __init__(self) -> None:
        self.answers = 0

    def set_result(self, _value: Any) -> None:
        self.answers += 1

    def set_error(self, _error: BaseException) -> None:
        self.answers += 1


def _lose_while_reading(system: System, answers: int) -> list[int]:
    """Close a peer's channel while a thread pops its answers; tokens not answered once."""
    peer = RemotePeer(system, f"nobody-{uuid.uuid4().hex[:8]}")
    channel = _Channel(_Writer(None, lambda _exc: None))
    peer._channel = channel
    replies = {token: _CountingReply() for token in range(1, answers + 1)}
    channel.pending.update((token, (reply, None)) for token, reply in replies.items())
    go = threading.Event()

    def reader() -> None:  # what the reader thread does with each answer
        go.wait(10)
        for token in reversed(replies):
            entry = channel.pending.pop(token, None)
            if entry is not None:
                entry[0].set_result(None)

    thread = threading.Thread(target=reader)
    thread.start()
    go.set()
    try:
        peer.close(rr.RegistrarStoppedError("closing"))
    finally:
        thread.join(10)
    return [token for token, reply in replies.items() if reply.answers != 1]


def test_losing_a_connection_while_its_reader_resolves_answers_answers_each_reply_once(
    system: System,
) -> None:
    switch_interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible
    try:
        trials = [_lose_while_reading(system, 100_000) for _ in range(5)]
    finally:
        sys.setswitchinterval(switch_interval)

    assert [[]] * 5 == trials


# -- encoding: the C pickler's fast path ----------------------------------------------------


class _MyStr(str):
    """A subclass of a builtin: not plain."""


def _nested(depth: int) -> list[Any]:
    value: list[Any] = []
    for _ in range(depth):
        value = [value]
    return value


@pytest.mark.parametrize(
    "value",
    [
        Load("q1", "leaf", {"cmd": ["driver", "--id", 7], "rate": 2.5}, "C", ("C",), None),  # type: ignore[arg-type]
        Fetch("leaf", "C", None),  # type: ignore[arg-type]
        rr.Query("q2", "leaf", "P", "C", ("a", 1), {"pid": 4}),
        ("answer", 3, None, b"x", frozenset({1}), {2, 3}),
        rr.Status.FATAL,
    ],
)
def test_small_builtin_data_is_pickled_by_the_c_pickler_as_cloudpickle_would(value: Any) -> None:
    from rr_actors._transport import unix as _transport  # noqa: PLC0415 - private helpers under test

    assert _transport._plain(value)
    frame = _transport._frame(9, value)
    token, payload = _transport._unframe(frame[4:])
    assert token == 9
    assert pickle.loads(payload) == value
    assert bytes(payload) == cloudpickle.dumps(value, pickle.HIGHEST_PROTOCOL)


@pytest.mark.parametrize(
    "value",
    [
        {"f": lambda: 1},  # needs cloudpickle
        [_MyStr("x")],  # a subclass
        Load("q1", "leaf", {"at": uuid.UUID(int=1)}, "C", (), None),  # not builtin data
        list(range(300)),  # too wide
        _nested(70),  # too deep
    ],
)
def test_anything_else_goes_through_cloudpickle(value: Any) -> None:
    from rr_actors._transport import unix as _transport  # noqa: PLC0415 - private helpers under test

    assert not _transport._plain(value)
    token, payload = _transport._unframe(_transport._frame(1, value)[4:])
    assert token == 1
    decoded = cloudpickle.loads(payload)
    if not isinstance(value, dict):
        assert decoded == value


def test_a_writer_closed_while_a_sender_writes_still_ends_its_thread_and_socket() -> None:
    # close() wakes the writer thread before the sender is done; the sender, finishing
    # with nothing queued, must wake it again or it waits for `_busy` forever
    entered, release, sock_closed, in_final_wait = (threading.Event() for _ in range(4))

    class Socket:  # holds the sender inside its send() until told
        def send(self, data: bytes, flags: int) -> int:
            entered.set()
            release.wait(10)
            return len(data)

        def shutdown(self, how: int) -> None:
            pass

        def close(self) -> None:
            sock_closed.set()

    writer = _Writer(Socket(), lambda exc: None)  # type: ignore[arg-type]

    class Cond(threading.Condition):
        def wait(self, timeout: float | None = None) -> bool:
            if writer.closed:  # the writer thread waits for the sender to finish
                in_final_wait.set()
            return super().wait(timeout)

    writer._cond = Cond(threading.Lock())
    writer.start("test-writer")
    thread = next(t for t in threading.enumerate() if t.name == "test-writer")
    sender = threading.Thread(target=writer.send, args=(b"frame",))
    sender.start()
    assert entered.wait(10)
    writer.close()
    assert in_final_wait.wait(10)
    release.set()
    sender.join(10)
    thread.join(10)
    assert not thread.is_alive()
    assert sock_closed.is_set()


def test_a_load_crosses_without_its_reply_and_otherwise_unchanged() -> None:
    from rr_actors._transport import unix as _transport  # noqa: PLC0415 - private helper under test

    load = Load("q", "leaf", {"n": 1}, "C", ("C",), object())  # type: ignore[arg-type]
    assert _transport._without_reply(load) == dataclasses.replace(load, reply=None)


# -- cutting frames out of the byte stream ------------------------------------------------------


def _frames_of(chunks: list[bytes]) -> list[bytes]:
    """What `_frames` yields for a peer that writes `chunks` one by one, then closes."""
    ours, theirs = socket.socketpair()
    conn = multiprocessing.connection.Connection(ours.detach())
    got: list[bytes] = []
    reader = threading.Thread(target=lambda: got.extend(_frames(conn)))
    reader.start()
    with theirs:
        for chunk in chunks:
            theirs.sendall(chunk)
    reader.join(10)
    conn.close()
    return got


def _wire(payload: bytes) -> bytes:
    return struct.pack("!i", len(payload)) + payload


def test_many_frames_that_arrive_in_one_read_are_each_handed_on() -> None:
    payloads = [b"a", b"", b"bb" * 1000, b"c" * 70_000]

    assert payloads == _frames_of([b"".join(_wire(p) for p in payloads)])


def test_a_frame_that_arrives_a_byte_at_a_time_is_handed_on_whole() -> None:
    wire = _wire(b"hello") + _wire(b"world")

    assert [b"hello", b"world"] == _frames_of([wire[i : i + 1] for i in range(len(wire))])


def test_a_frame_larger_than_a_read_is_handed_on_whole() -> None:
    big = bytes(range(256)) * 4_000  # 1 MB: four reads' worth

    assert [big, b"after"] == _frames_of([_wire(big) + _wire(b"after")])


def test_the_long_header_of_multiprocessing_connection_is_understood() -> None:
    # Frames over 2 GiB carry -1 and then an 8-byte length; any size may use it.
    assert [b"long", b"short"] == _frames_of(
        [struct.pack("!iQ", -1, 4) + b"long" + _wire(b"short")]
    )


def test_a_connection_that_ends_inside_a_frame_hands_on_only_the_whole_ones() -> None:
    assert [b"whole"] == _frames_of([_wire(b"whole") + struct.pack("!i", 10) + b"cut"])


def test_frames_read_match_what_connection_recv_bytes_reads() -> None:
    frames = [_frame(token, value) for token, value in enumerate([1, "two", {"three": [3]}])]

    got = _frames_of([b"".join(frames)])

    left, right = multiprocessing.Pipe()
    with left, right:
        for frame in frames:
            left.send_bytes(frame[4:])  # the payload; send_bytes adds the same header
        expected = [right.recv_bytes() for _ in frames]
    assert expected == got
