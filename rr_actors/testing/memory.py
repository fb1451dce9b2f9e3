"""An in-memory carrier: a test double of a system of registrars across processes.

`MemoryNetwork` is a carrier (a `Transport`, like an AF_UNIX `System` or a `ZenohNetwork`)
whose "processes" are in this one: every registrar served on it counts as running in a
process of its own. It carries frames (pickled, `codec.frame`), never Python objects, so
unpicklable or oversized messages behave as across processes; everything else is the
messenger's (`rr_actors._transport.messenger`); this file is only the link:

```
 network.resolve(name).tell(m) ─► messenger: encode, check size, keep the reply ─►
   hub.send(route, frame) ─► the delivery thread of `name` (rr-mem-<name>) ─► its process's
   messenger: unpickle, stand-in reply, tell the registrar ─► answer frame ─►
   hub.answer(route) ─► the answers thread (rr-mem-answers) ─► the route's `pending`
```

Registrars of one process find each other in its directory first: only what a test sends
through `resolve` and `run` crosses this carrier (docs/reference/testing.md). It joins no
other process, has no lease and reports no registrar lost (rule 19) or reachable (rule 20).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rr_actors._core import runtime
from rr_actors._core.serial import SerialExecutor, Task
from rr_actors._transport.codec import split_frame
from rr_actors._transport.messenger import (
    Address,
    Carrier,
    Endpoint,
    Listening,
    Lost,
    Messenger,
    Route,
    Transport,
    run_lost,
)
from rr_actors._transport.resolve import Sided
from rr_actors.config import check_seconds
from rr_actors.errors import (
    ConfigError,
    DuplicateNameError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownRegistrarError,
    _known_names,
)

__all__ = ["MemoryAddress", "MemoryNetwork"]

_NETWORKS: dict[str, MemoryNetwork] = {}  # by system name: what `MemoryAddress` attaches


class _Members:
    """This process's memberships of in-memory networks, by system name: the network
    itself in the process that made it; in another simulated process (a simulation runs
    each of its processes on one network), a `_Member` made at its first `attach`."""

    def __init__(self) -> None:
        self.by_system: dict[str, MemoryNetwork | _Member] = {}


_MEMBERS = runtime.process_state(_Members(), _Members)


@dataclasses.dataclass(frozen=True)
class MemoryAddress:
    """How to join a `MemoryNetwork`: it pickles; `attach()` works in this process only.

    Attributes:
        system: the network's name.
    """

    system: str

    def attach(self) -> Transport:
        """The network of that name (this process's); in another simulated process, that process's
        membership of it (a new one once it left).

        Raises:
            RegistrarStoppedError: it was closed, or it is another process's.
        """
        network = _NETWORKS.get(self.system)
        if network is None:
            raise RegistrarStoppedError(
                f"no in-memory network {self.system!r} in this process (closed, or another "
                f"process's: an in-memory network cannot be joined from another process)"
            )
        member = _MEMBERS.by_system.get(self.system)
        left = member is not None and member.closed
        if member is None or left or member.link() is not network.link():
            member = _Member(self.system, resolve=network.resolution.resolve)
            member.joined(network.link())
            _MEMBERS.by_system[self.system] = member
        return member


class _Member(Messenger):
    """A simulated process's membership of a network another one made (`attach`): the
    directory of that process asks it for names. Leaving is its process's end (the
    simulation cuts what it served); its `close` stops serving here, the network stays."""

    leaves = False

    @property
    def address(self) -> MemoryAddress:
        return MemoryAddress(self.system)


class _Served(Listening):
    """A registrar served on the network: its "process", its delivery thread."""

    def __init__(self, hub: _Hub, endpoint: Endpoint, messenger: Messenger) -> None:
        super().__init__(endpoint)
        self.hub = hub
        self.inbox = SerialExecutor(f"rr-mem-{endpoint.name}")
        self.inbox.start()  # (now: its thread is the serving process's)
        self.route = _Route(self, messenger)  # every sender's: what waits on it
        self.cut = False  # its process is gone
        self.gone = False  # no longer reached


class _Route(Route):
    """The way to one served registrar: its delivery thread; one per served registrar,
    shared by every sender (their replies wait on it)."""

    __slots__ = ("messenger", "served")

    def __init__(self, served: _Served, messenger: Messenger) -> None:
        super().__init__(served.endpoint.max_message_bytes)
        self.served = served
        self.messenger = messenger

    def put(self, data: bytes) -> bool:
        """`_Hub.send`; False if nothing of `data` left."""
        served = self.served
        if served.cut or served.gone:
            return False
        endpoint, messenger = served.endpoint, self.messenger
        token, payload = split_frame(data)
        return served.inbox.submit(lambda: messenger.message(endpoint, self, token, payload))


class _Hub:
    """The network between the "processes" (every one's `Carrier`): who serves what,
    the answers thread. What reaches a served registrar is handed to the network's
    messenger (any of theirs would do: none keeps state of a message)."""

    def __init__(self, messenger: Messenger) -> None:
        self.messenger = messenger
        self.system = messenger.system
        self.closed = False
        self._lock = runtime.Lock()
        self._served: dict[str, _Served] = {}
        self._gone: dict[str, str] = {}  # name -> "stopped" | "unavailable"
        self._answers = SerialExecutor("rr-mem-answers", on_drop=_lost)
        self._answers.start()  # (now: its thread is the network's process's)

    def names(self) -> list[str]:
        return [name for name, served in list(self._served.items()) if not served.cut]

    def knows(self, name: str) -> bool:
        return name in self._served or name in self._gone

    def serve(self, endpoint: Endpoint) -> _Served:
        """Serve `endpoint` in a "process" of its own (one name, one registrar).

        Raises:
            DuplicateNameError: another "process" serves that name.
            RegistrarStoppedError: the network was closed.
        """
        served, name = self.served(endpoint), endpoint.name
        with self._lock:
            old = self._served.get(name)
            if old is not None and old.endpoint.wait_ended(0):
                del self._served[name]  # (its registrar ended: it went, as after a kill)
            else:
                old = None
            refused = self.closed or name in self._served
            if not refused:
                self._served[name] = served
                self._gone.pop(name, None)
        if refused:
            served.inbox.close(timeout=0)
            if self.closed:
                raise RegistrarStoppedError("the in-memory network was closed")
            raise self.duplicate_error(name, "another process")
        if old is not None:
            self.end(old, "unavailable")
        return served

    def duplicate_error(self, name: str, by: str) -> DuplicateNameError:
        """What `serve` raises for a name `by` serves (one name, one registrar)."""
        return DuplicateNameError(
            f"a registrar named {name!r} is already served on system {self.system!r} (by {by})"
        )

    def served(self, endpoint: Endpoint) -> _Served:
        """A new `_Served` for `endpoint`, complete before anyone can route to it."""
        return _Served(self, endpoint, self.messenger)

    def unserve(self, listening: Listening, *, stopped: bool) -> None:
        assert isinstance(listening, _Served)
        self.end(listening, "stopped" if stopped else "unavailable")

    def route(self, name: str, server: Sided | None = None) -> Route:
        """`name`'s one server: this network never sees two, so no other (`server`)."""
        if server is not None:
            raise RegistrarUnavailableError(f"no second server of {name!r} is seen here")
        served = self._served.get(name)
        if served is None or served.cut or served.gone:
            raise self.gone_error(name)
        return served.route

    def send(self, route: Route, data: bytes) -> None:
        assert isinstance(route, _Route)
        if not route.put(data):
            raise self.gone_error(route.served.name)

    def gone_error(self, name: str) -> RrError:
        if self.closed:
            return RegistrarStoppedError(f"the in-memory network {self.system!r} was closed")
        if self._gone.get(name) == "stopped":
            return RegistrarStoppedError(f"registrar {name!r} was stopped", name)
        return RegistrarUnavailableError(f"registrar {name!r} cannot be reached (its process went)")

    def answer(self, process: _Route, data: bytes, on_lost: Lost | None) -> bool:
        """Send an answer back over the route its message came by (`process`): on the
        answers thread, to the route's waiting replies; False if the route went."""
        if process.served.cut or self.closed:
            return False
        return self._answers.submit(_Answer(process, data, on_lost))

    def cut(self, name: str) -> None:
        served = self._served.get(name)
        if served is not None:
            self.end(served, "unavailable")
        elif name not in self._gone:
            raise UnknownRegistrarError(
                f"no registrar named {name!r} was served on the in-memory network "
                f"{self.system!r}" + _known_names(name, self._served)
            )

    def end(self, served: _Served, how: str, error: RrError | None = None) -> None:
        """`served` is no longer reached: what waits on it fails (`how` says why)."""
        with self._lock:
            if served.gone:
                return
            served.gone = True
            served.cut = how == "unavailable"
            if self._served.get(served.name) is served:
                del self._served[served.name]
            self._gone[served.name] = how
        served.inbox.close(timeout=0)
        error = error or self.gone_error(served.name)
        served.route.pending.fail(None, error)

    def leave(self) -> None:
        """The network closes (only the network's own messenger leaves)."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            served = list(self._served.values())
            self._served.clear()
        for one in served:
            self.end(one, "stopped", RegistrarStoppedError("the in-memory network was closed"))
        self._answers.close(timeout=0)


def open_networks() -> dict[str, MemoryNetwork]:
    """This process's in-memory networks still open, by name (a copy)."""
    return dict(_NETWORKS)


def free_names(but: dict[str, MemoryNetwork]) -> None:
    """Free the name of every open network that is not in `but` (`open_networks()` taken
    before): as a simulated run that made them ends, however its cleanup went (their
    tasks and threads are gone, so they are not closed)."""
    for network in [n for n in _NETWORKS.values() if but.get(n.system) is not n]:
        network._free_name()


class MemoryNetwork(Messenger):
    """An in-memory system of registrars, each in a "process" of its own (see the module
    docstring): a `Transport` test double.

    Args:
        system: its name (`MemoryAddress` finds it by that name in this process).

    Raises:
        ConfigError: another open network of this process has that name.
    """

    _hub_class: type[_Hub] = _Hub
    """What carries its frames between its "processes" (a simulation's adds faults)."""

    def __init__(self, system: str = "memory") -> None:
        if system in _NETWORKS:
            raise ConfigError(f"system: an in-memory network named {system!r} is open already")
        # (in a simulation, its process is one of the network's, as the others are)
        super().__init__(system, resolver=runtime.simulated())
        self._hub = self._hub_class(self)
        self.joined(self._hub)
        _NETWORKS[system] = self
        _MEMBERS.by_system[system] = self

    @property
    def address(self) -> MemoryAddress:
        """What `attach()`es to this network (in this process)."""
        return MemoryAddress(self.system)

    def serve(self, endpoint: Endpoint) -> None:
        """Serve a registrar of this process on the network until it ends.

        Raises:
            DuplicateNameError: another registrar served on it has that name.
            RegistrarStoppedError: the network was closed.
        """
        process = Messenger(self.system, resolver=False)
        process.joined(self._hub)
        process.serve(endpoint)

    def run(self, name: str, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """Run `fn(registrar)` where registrar `name` lives, through the carrier (`Transport.run`).

        Raises:
            UnknownServerError: nobody serves that name on the network.
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: it was cut off (`cut`), or it died.
            RegistrarStoppedError: it was stopped.
            ConfigError: `timeout` is not a positive number of seconds.
        """
        check_seconds("timeout", timeout)
        return super().run(name, fn, timeout=timeout)

    def close(self) -> None:
        """Stop serving; what waits fails with `RegistrarStoppedError` (idempotent)."""
        super().close()
        self._free_name()

    def _free_name(self) -> None:
        """Free its name for the next network of this process (once it is closed, or a
        simulated run that made it is over, however its cleanup went)."""
        if _NETWORKS.get(self.system) is self:
            del _NETWORKS[self.system]
        if _MEMBERS.by_system.get(self.system) is self:
            del _MEMBERS.by_system[self.system]

    def cut(self, name: str) -> None:
        """The process serving `name` is gone (a `SIGKILL`): replies waiting on it fail at once with
        `RegistrarUnavailableError`, frames to it are dropped, later sends raise. Its registrar
        runs on here (stop it yourself). Cutting again does nothing.

        Raises:
            UnknownRegistrarError: no registrar of that name was ever served on the network.
        """
        self._hub.cut(name)


class _Answer:
    """One answer frame on its way back (a task of the answers thread)."""

    __slots__ = ("data", "on_lost", "route")

    def __init__(self, route: _Route, data: bytes, on_lost: Lost | None) -> None:
        self.route = route
        self.data = data
        self.on_lost = on_lost

    def __call__(self) -> None:
        self.route.pending.answered(*split_frame(self.data))


def _lost(task: Task) -> None:
    if isinstance(task, _Answer) and task.on_lost is not None:
        run_lost([task.on_lost])


if TYPE_CHECKING:  # mypy checks that the double is a carrier
    _transport: type[Transport] = MemoryNetwork
    _address: type[Address] = MemoryAddress
    _carrier: type[Carrier] = _Hub
