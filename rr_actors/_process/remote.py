"""A registrar's actor in another process of a system, and the handle on it.

A `RemoteRegistrar` is the one handle (`Registrar`) whose actor is `There`: each
operation runs where the registrar is, over the system's carrier:

```
 reg.call(...) / await reg.acall(...) ─► There.steps(Here.call, timeout, ...)
   served by this process ──────────────► its ResourceRegistrar's Here.call, here (so a
                                          call inside a load is still its dependency)
   served by another ───────────────────► submit one Run(_drive_there): there, on a thread
                                          of its own, run_steps(Here.call(...)) in the
                                          caller's load context
     ◄── its answer settles the Run's future: it wakes the thread or the loop here,
         a `FORWARD_MARGIN` beyond the operation's own timeout
   cancelled, or timed out here ────────► what the call there still gets is given back
                                          (its id released there), as a withdrawn call's
```

The owner of a manager process (`RemoteRegistrar.start`) holds it as `Owner`, a `There`
whose stop and liveness are the process's (its death unstopped is a death watch).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import Any, Concatenate, ParamSpec, TypeVar, cast

from rr_actors._core import traces, wire
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.replies import Steps, on_own_thread, run_steps
from rr_actors._process.manager import ManagerExit, ManagerProcess
from rr_actors._registrar.handle import Here, Registrar, RegistrarFacts, ResourceRegistrar
from rr_actors._registrar.life import gone_for_good
from rr_actors._registrar.messages import LOADING, LoadContext
from rr_actors._transport.messenger import Address, Remote, Transport
from rr_actors._types import Query
from rr_actors.config import RegistrarConfig
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
)

T = TypeVar("T")
P = ParamSpec("P")

FORWARD_MARGIN = 10.0
"""Seconds an operation run in another process may take beyond its own `timeout`."""


class There:
    """The actor in another process of the system (or in this one, found by its name)."""

    def __init__(self, config: RegistrarConfig, address: Address) -> None:
        self.config = config
        self.address = address  # (any carrier's `Address`: it pickles)

    def steps(
        self,
        op: Callable[Concatenate[Here, float | None, P], Steps[T]],
        timeout: float | None,
        *args: P.args,
        **kwargs: P.kwargs,
    ) -> Steps[T]:
        name = self.config.name
        limit = _margin(timeout, self.config)
        transport = self.address.attach()
        peer = transport.resolve(name)
        if not isinstance(peer, Remote):  # served here (or unknown: `run` says so)
            local: ResourceRegistrar = transport.run(name, _itself, timeout=limit)
            return (yield from op(local._actor, timeout, *args, **kwargs))
        there = functools.partial(
            _drive_there, op, timeout, args, kwargs, LOADING.get(), traces.current()
        )
        reply = peer.submit(there)
        try:
            settled = yield reply.future, time.monotonic() + limit
        except BaseException:
            reply.future.add_done_callback(functools.partial(_give_back, peer))
            raise
        if not settled:
            reply.future.add_done_callback(functools.partial(_give_back, peer))
            raise CallTimeoutError(f"run() on registrar {name!r} timed out after {limit:g} s")
        result: T = reply.future.get(timeout=0)
        return result

    def stop(self, timeout: float | None) -> Steps[None]:
        limit = self.config.call_timeout if timeout is None else timeout
        with contextlib.suppress(RegistrarStoppedError, RegistrarUnavailableError):
            yield from self.steps(Here.stop, limit)

    def is_alive(self) -> bool:
        try:
            return bool(self.run(_is_alive, self.config.call_timeout + FORWARD_MARGIN))
        except RrError:
            return False

    def state(self) -> str:
        return ""

    @property
    def pid(self) -> int | None:
        return None

    def run(self, fn: Callable[[ResourceRegistrar], Any], timeout: float | None) -> Any:
        limit = self.config.call_timeout if timeout is None else timeout
        return self.address.attach().run(self.config.name, fn, timeout=limit)

    def kill(self, timeout: float) -> None:
        """Not the owner: it SIGKILLs itself, and its owner does the rest."""
        with contextlib.suppress(RegistrarUnavailableError, RegistrarStoppedError):
            self.run(_kill_own_process, timeout)


class Owner(There):
    """The actor in a manager process this process started and owns."""

    def __init__(self, config: RegistrarConfig, address: Address) -> None:
        super().__init__(config, address)
        self.process: ManagerProcess | None = None  # (set once it was started)
        self.stopping = False
        self.down = threading.Event()  # the process ended, its death watch told

    @classmethod
    def start(
        cls, config: RegistrarConfig, address: Address, setup: bytes, start_timeout: float
    ) -> Owner:
        owner = cls(config, address)
        owner.process = ManagerProcess.start(
            config.name,
            setup,
            config,
            address,
            start_timeout=start_timeout,
            heartbeat=None,
            heartbeat_timeout=start_timeout,
            on_exit=owner._exited,
        )
        return owner

    def stop(self, timeout: float | None) -> Steps[None]:
        stop = functools.partial(self._stop_process, timeout)
        return on_own_thread(stop, f"rr-stop-{self.config.name}")

    def _stop_process(self, timeout: float | None) -> None:
        limit = self.config.call_timeout if timeout is None else timeout
        process = self._process()
        if process.exited.is_set():
            return
        self.stopping = True
        result = process.stop(limit)
        self.down.wait(limit)
        if result.normal:
            return
        name = self.config.name
        if result.reason.startswith("killed: no clean stop"):
            raise CallTimeoutError(f"stop() of registrar {name!r}: {result.reason}")
        raise RegistrarUnavailableError(f"registrar {name!r} did not stop cleanly: {result.reason}")

    def is_alive(self) -> bool:
        return not self._process().exited.is_set()

    def state(self) -> str:
        return f"pid {self.pid}"

    @property
    def pid(self) -> int | None:
        return self._process().pid

    def kill(self, timeout: float) -> None:
        self._process().kill()
        if not self.down.wait(timeout):
            raise CallTimeoutError(f"manager {self.config.name!r} not dead within {timeout:g} s")

    def _process(self) -> ManagerProcess:
        assert self.process is not None, "the manager process was not started"
        return self.process

    def _exited(self, how: ManagerExit) -> None:
        """The process ended (its watcher thread): unless stopped or a restart is expected,
        its death watch (rule 19)."""
        try:
            name = self.config.name
            if not how.clean and not self.stopping and not DIRECTORY.restart_expected(name):
                served: list[str] = []
                with contextlib.suppress(RrError):
                    served = self.address.attach().names()
                gone_for_good(name, also=served)
        finally:
            self.down.set()


class RemoteRegistrar(Registrar):
    """A handle on a registrar that lives in a manager process of a system.

    The one handle, [`Registrar`][rr_actors.Registrar] (same arguments, results and
    errors), whose actor is in that process: each method runs there, over the system's
    carrier. Arguments, callbacks and results are cloudpickled (callbacks may be
    closures) and callbacks run in the registrar's process, on the threads a local
    registrar would use. The handle pickles; in the registrar's own process it calls the
    registrar directly (a call inside a `load` is still a dependency).

    [`start`][rr_actors.testing.RemoteRegistrar.start] returns the *owner* handle, which
    can [`kill`][rr_actors.testing.RemoteRegistrar.kill] the process; the constructor
    reaches an existing registrar. An owned process that dies unstopped is a death watch
    (rule 19), unless a restart is expected (`rr_actors.testing.expect_restart`).
    """

    _actor: There

    def __init__(
        self,
        config: RegistrarConfig | str,
        address: Address,
        *,
        restored: bool = False,
        in_doubt: tuple[Query, ...] = (),
    ) -> None:
        """Make a handle on the running registrar `config.name` of the system at `address`.

        Args:
            config: the registrar's configuration (its `call_timeout` is the default
                timeout of this handle's methods), or just its name.
            address: the system's address (any carrier's `Address`; it pickles).
            restored: what `restored` reports.
            in_doubt: what `in_doubt` reports.
        """
        config = RegistrarConfig(name=config) if isinstance(config, str) else config
        super().__init__(RegistrarFacts(config, restored, in_doubt), There(config, address))

    @classmethod
    def start(
        cls,
        config: RegistrarConfig | str,
        system: Transport | Address,
        *,
        setup: Callable[[ResourceRegistrar], None] | None = None,
        start_timeout: float = 10.0,
    ) -> RemoteRegistrar:
        """Start a registrar in a new manager process of `system`; return the owner handle.

        There it restores its catalog, runs `setup(registrar)` and serves; it dies with
        this process.

        Args:
            config: the registrar's configuration, or just its name.
            system: the system the registrar joins: any carrier's `Transport` (the
                AF_UNIX `System`, a `ZenohNetwork`) or its `Address`.
            setup: cloudpickled and run in the manager process before it serves.
            start_timeout: seconds the manager may take to be ready.

        Returns:
            The owner handle.

        Raises:
            ConfigError: `config` is invalid or `setup` does not pickle.
            CatalogCorruptError: its backup cannot be read (with its `path`).
            RegistrarUnavailableError: the manager failed to start otherwise (its
                traceback is in the message).
            CallTimeoutError: it was not ready within `start_timeout` seconds.
        """
        if isinstance(config, str):
            config = RegistrarConfig(name=config)
        elif not isinstance(config, RegistrarConfig):
            raise ConfigError(f"config must be a RegistrarConfig or a name, got {config!r}")
        address = cast("Address", getattr(system, "address", system))
        try:
            payload = wire.dumps(setup)  # (its code keeps its file: a traceback shows it)
        except Exception as exc:
            raise ConfigError(
                f"setup of registrar {config.name!r} is not picklable: {exc}"
            ) from exc
        handle = cls(config, address)
        handle._actor = Owner.start(config, address, payload, start_timeout)
        try:
            restored, in_doubt = handle.run(_restored_and_in_doubt, timeout=start_timeout)
            handle._facts = RegistrarFacts(config, restored, in_doubt)
        except BaseException:
            handle.kill()
            raise
        return handle

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickle as a plain (non-owner) handle."""
        facts = self._facts
        return (_rebuild, (facts.config, self._actor.address, facts.restored, facts.in_doubt))

    @property
    def pid(self) -> int | None:
        """The manager process's pid (owner handle), else `None`."""
        return self._actor.pid

    def run(self, fn: Callable[[ResourceRegistrar], Any], *, timeout: float | None = None) -> Any:
        """Run `fn(registrar)` in the registrar's process and return its result.

        `fn` is cloudpickled; in the registrar's own process it runs on the calling
        thread, elsewhere on a fresh thread of the registrar's process.

        Args:
            fn: called with the `ResourceRegistrar`; its result must pickle.
            timeout: seconds to wait for the result (default: the config's `call_timeout`).

        Returns:
            What `fn` returned.

        Raises:
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: the registrar's process died or is unreachable.
            RegistrarStoppedError: the registrar was stopped.
            UnknownServerError: no registrar of that name was ever served on the system.
            ConfigError: `fn` does not pickle.
            Exception: whatever `fn` raised, re-raised here.
        """
        return self._actor.run(fn, timeout)

    def kill(self, *, timeout: float = 5.0) -> None:
        """SIGKILL the registrar's manager process; return once it is dead.

        The owner handle also waits until the death watch went out.

        Args:
            timeout: seconds to wait for the death.

        Raises:
            CallTimeoutError: it was not seen dead within `timeout` seconds.
        """
        self._actor.kill(timeout)


def _margin(timeout: object, config: RegistrarConfig) -> float:
    """How long to wait for an operation there (an invalid `timeout`, which the registrar
    rejects, waits the default)."""
    valid = isinstance(timeout, int | float) and not isinstance(timeout, bool) and timeout > 0
    limit = float(cast("float", timeout)) if valid else config.call_timeout
    return limit + FORWARD_MARGIN


def _drive_there(
    op: Callable[..., Steps[T]],
    timeout: float | None,
    args: tuple[Any, ...],
    kwargs: dict[str, Any],
    context: LoadContext | None,
    traceparent: str,
    registrar: ResourceRegistrar,
) -> T:
    """In the registrar's process: run the operation's steps in the caller's load context
    and OpenTelemetry span (`traceparent`, `""`: none)."""
    steps = functools.partial(op, registrar._actor, timeout, *args, **kwargs)
    if context is None and not traceparent:
        return run_steps(steps())
    scope = contextvars.copy_context()
    if context is not None:
        scope.run(LOADING.set, context)
    if traceparent:
        scope.run(traces.adopt, traceparent)
    return scope.run(lambda: run_steps(steps()))


def _give_back(peer: Remote, future: Any) -> None:
    """A call whose caller stopped waiting got its answer there: release its query there."""
    try:
        query = future.get(timeout=0)
    except Exception:  # noqa: BLE001 - failed there: nothing is held
        return
    if isinstance(query, Query):
        peer.submit(functools.partial(_release, query.id))


def _release(query_id: str, registrar: ResourceRegistrar) -> None:
    with contextlib.suppress(RrError):
        registrar.unload(query_id)


def _rebuild(
    config: RegistrarConfig, address: Address, restored: bool, in_doubt: tuple[Query, ...]
) -> RemoteRegistrar:
    return RemoteRegistrar(config, address, restored=restored, in_doubt=in_doubt)


def _restored_and_in_doubt(registrar: ResourceRegistrar) -> tuple[bool, tuple[Query, ...]]:
    return registrar.restored, registrar.in_doubt


def _itself(registrar: ResourceRegistrar) -> ResourceRegistrar:
    return registrar


def _is_alive(registrar: ResourceRegistrar) -> bool:
    return registrar.is_alive()


def _kill_own_process(_: ResourceRegistrar) -> None:
    os.kill(os.getpid(), signal.SIGKILL)
