"""What the transport tests share: provider processes, their callbacks, the fixtures.

Each provider registrar runs in a child process started with the "forkserver" context: the
child joins the system (`address.attach()`), starts a registrar, runs a setup function
(cloudpickled), serves the registrar, says "ready" over a pipe and waits until the pipe
says "stop" (or closes: a child never outlives the test process). The consumer is in the
test process.

Functions that read a child's state (`load_count`, `wait_load_started`, ...) are module
level, so cloudpickle sends them by reference and they run against the child's globals.
The `system` fixture runs a test once per carrier (`CARRIERS`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import multiprocessing.forkserver
import multiprocessing.synchronize
import os
import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import cloudpickle
import pytest

import rr_actors as rr
from rr_actors._registrar.life import Served
from rr_actors._transport import System, Transport

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


def _span_load(_request: Any) -> str:
    """The W3C traceparent of the OpenTelemetry span current in the load ("" if none)."""
    from opentelemetry import trace  # noqa: PLC0415 - the otel extra, only where used

    span = trace.get_current_span().get_span_context()
    if not span.is_valid:
        return ""
    return f"00-{span.trace_id:032x}-{span.span_id:016x}-{span.trace_flags:02x}"


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


def _sized_load(size: int) -> bytes:
    return b"x" * size


def setup_servers(registrar: rr.ResourceRegistrar) -> None:
    """The provider's servers: a recording `echo`, a `slow` one, one with a bad response
    (`lock`), `sized`, whose response to `n` is `n` bytes, and `span`, whose response is
    the traceparent of the OpenTelemetry span its load ran under."""
    registrar.register_server("echo", load=_record_load, unload=_record_unload)
    registrar.register_server("span", load=_span_load, unload=_record_unload)
    registrar.register_server("sized", load=_sized_load, unload=_record_unload)
    registrar.register_server("gated", load=_gated_load, unload=_record_unload)
    registrar.register_server("slow", load=_blocking_load, unload=_record_unload)
    registrar.register_server("lock", load=lambda _request: threading.Lock(), unload=_record_unload)


def bytes_read(pid: int) -> int:
    """How many bytes process `pid` has read so far (sockets included; Linux's `rchar`)."""
    with open(f"/proc/{pid}/io", encoding="ascii") as io:
        fields = dict(line.split(": ") for line in io.read().splitlines())
    return int(fields["rchar"])


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


PROVIDER_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
"""The providers' `max_message_bytes` unless a test says otherwise: `BIG` answers pass."""


def provider_main(
    address: Any,
    name: str,
    setup: bytes,
    control: multiprocessing.connection.Connection,
    config: dict[str, Any] | None = None,
) -> None:
    """A provider process: serve a registrar until told to stop (or the parent is gone).

    `config` holds `RegistrarConfig` fields beyond its name and `call_timeout` (10 s).
    """
    settings = {"max_message_bytes": PROVIDER_MAX_MESSAGE_BYTES, **(config or {})}
    attached = address.attach()
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=name, call_timeout=10.0, **settings)
    )
    try:
        cloudpickle.loads(setup)(registrar)
        attached.serve(Served(registrar))
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        CHILD.release.set()
        registrar.stop()
        attached.close()


# -- rule 19: an endpoint that records what it hears, a provider nobody supervises ----------


class Recorder:
    """An `Endpoint` that records the presence callbacks it gets (no registrar behind it):
    `lost` and `reachable`, each `(name, monotonic time)`; `heard` is set by either."""

    def __init__(self, name: str | None = None) -> None:
        self.name = name or f"recorder-{uuid.uuid4().hex[:8]}"
        self.max_message_bytes = 1024 * 1024
        self.lost: list[tuple[str, float]] = []
        self.reachable: list[tuple[str, float]] = []
        self.heard = threading.Event()
        self.changed = threading.Condition()
        self._ended = threading.Event()

    def run(self, fn: Callable[[Any], Any]) -> Any:
        return fn(None)

    def wait_ended(self, timeout: float | None = None) -> bool:
        return self._ended.wait(timeout)

    def stopped_cleanly(self) -> bool:
        return self._ended.is_set()

    def listening(self) -> None:
        pass

    def peer_lost(self, name: str) -> None:
        with self.changed:
            self.lost.append((name, time.monotonic()))
            self.heard.set()
            self.changed.notify_all()

    def peer_reachable(self, name: str) -> None:
        self.reachable.append((name, time.monotonic()))
        self.heard.set()

    def lost_names(self) -> list[str]:
        with self.changed:
            return [name for name, _ in self.lost]

    def wait_lost(self, name: str, timeout: float = 5.0) -> float | None:
        """When `name` was first reported lost (monotonic), waiting up to `timeout` s."""
        with self.changed:
            self.changed.wait_for(lambda: name in [n for n, _ in self.lost], timeout)
            return next((at for n, at in self.lost if n == name), None)

    def end(self) -> None:
        self._ended.set()


def own_provider_main(
    join: tuple[Any, ...], name: str, control: multiprocessing.connection.Connection
) -> None:
    """An unsupervised provider process: joins the system by itself (`join`: `("attach",
    address)`, or `("router", system, endpoint)` for a Zenoh router of its own), serves
    registrar `name` with the `carriers` servers until told to stop, then stops cleanly."""
    if join[0] == "attach":
        transport = join[1].attach()
    else:
        transport = rr.ZenohNetwork(system=join[1], connect=[join[2]], tls=None)
    registrar = rr.ResourceRegistrar.start(rr.RegistrarConfig(name=name, call_timeout=10.0))
    try:
        setup_servers(registrar)
        transport.serve(Served(registrar))
        control.send("ready")
        with contextlib.suppress(EOFError, OSError):
            control.recv()
    finally:
        registrar.stop()
        transport.close()


# -- fixtures -----------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def context() -> multiprocessing.context.ForkServerContext:
    """The forkserver context, with its helper processes started before any leak check."""
    ctx = multiprocessing.get_context("forkserver")
    assert isinstance(ctx, multiprocessing.context.ForkServerContext)
    ctx.set_forkserver_preload(["rr_actors", "rr_actors._transport", "cloudpickle"])
    multiprocessing.forkserver.ensure_running()
    return ctx


class Children:
    """Child processes of a test, each given a control pipe as its last argument; at the
    test's end each is told to stop on it and reaped (killed after 10 s)."""

    def __init__(self, context: multiprocessing.context.ForkServerContext) -> None:
        self.context = context
        self.started: list[tuple[multiprocessing.process.BaseProcess, Any]] = []

    def start(
        self, target: Callable[..., None], *args: Any, ready: bool = True, daemon: bool = True
    ) -> tuple[multiprocessing.process.BaseProcess, Any]:
        """Start `target(*args, control)` (once it says "ready", with `ready`): the process
        and this end of its control pipe."""
        parent_end, child_end = self.context.Pipe()
        process = self.context.Process(target=target, args=(*args, child_end), daemon=daemon)
        process.start()
        child_end.close()
        self.started.append((process, parent_end))
        if ready:
            assert parent_end.poll(30), "the child did not get ready"
            assert "ready" == parent_end.recv()
        return process, parent_end

    def close(self) -> None:
        for _, control in self.started:
            with contextlib.suppress(OSError):
                control.send("stop")
        for process, control in self.started:
            process.join(10)
            if process.is_alive():
                process.kill()
                process.join(5)
            control.close()
            with contextlib.suppress(ValueError):  # its sentinel now, not at a later GC
                process.close()


@pytest.fixture
def children(context: multiprocessing.context.ForkServerContext) -> Iterator[Children]:
    started = Children(context)
    yield started
    started.close()


def _zenoh_network() -> Transport:
    """A fresh Zenoh system on loopback: this process is its router (lease 1 s)."""
    return rr.ZenohNetwork(system=f"test-{uuid.uuid4().hex[:8]}", tls=None)


CARRIERS: dict[str, Callable[[], Transport]] = {"unix": System.create, "zenoh": _zenoh_network}
"""Every carrier the transport contract runs over, by name: makes a fresh system."""


@pytest.fixture(params=sorted(CARRIERS))
def system(request: pytest.FixtureRequest) -> Iterator[Transport]:
    """A fresh system on each carrier (AF_UNIX: runtime directory + authkey), closed after."""
    created = CARRIERS[request.param]()
    yield created
    created.close()


@pytest.fixture
def consumer(system: Transport) -> Iterator[rr.ResourceRegistrar]:
    """A consumer registrar in the test process, served on the system."""
    registrar = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"consumer-{uuid.uuid4().hex[:8]}", call_timeout=30.0)
    )
    system.serve(Served(registrar))
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
    context: multiprocessing.context.ForkServerContext, system: Transport
) -> Iterator[ProviderFactory]:
    """Start provider processes: `start_provider(setup, name=None, **config)`; all are reaped.

    Keyword arguments are `RegistrarConfig` fields of the provider's registrar.
    """
    started: list[Provider] = []

    def start(setup: Setup = setup_servers, name: str | None = None, **config: Any) -> Provider:
        name = name or f"provider-{uuid.uuid4().hex[:8]}"
        parent_end, child_end = context.Pipe()
        process = context.Process(
            target=provider_main,
            args=(system.address, name, cloudpickle.dumps(setup), child_end, config),
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
