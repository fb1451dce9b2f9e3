"""Where registrars find each other by name, and what a message is sent through.

A *peer* is anything with `tell(message)`: a registrar actor in this process, or a channel
to one in another process. The directory maps names to peers and remembers why a name went
away, so callers get the right error (stopped, died, or unavailable while its supervisor
brings it back); who is gone for good is `membership.py`'s. A forked child forgets its
parent's registrars (a handle of one gets a `RegistrarUnavailableError` that says so) but
keeps the resolvers (each carrier resets its own state).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any, Protocol

import pykka

from rr_actors._core import runtime
from rr_actors._core.actor import awaiting, deliver
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._platform import forkserver
from rr_actors.errors import (
    DuplicateNameError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    UnknownRegistrarError,
    _known_names,
)

logger = logging.getLogger("rr_actors")


class Reply(Protocol):
    """Where the answer to one request goes; called from any thread, at most once."""

    def set_result(self, value: Any) -> None: ...
    def set_error(self, error: BaseException) -> None: ...


class Peer(Protocol):
    """Something a message for a registrar can be sent through."""

    name: str

    def tell(self, message: Any) -> None:
        """Send `message`; raise `RegistrarUnavailableError` if the registrar is dead."""

    def deliver(self, message: Any) -> None:
        """`tell` from a thread holding no lock (a carrier's reader; a loop's, to a non-durable
        registrar): an idle local registrar may handle it there."""


class LocalPeer:
    """A registrar actor in this process (`ref` set when it starts); a `durable` one's steps write
    to disk before they answer, so a loop's thread never takes its turn."""

    def __init__(
        self, name: str, ref: pykka.ActorRef[Any] | None = None, *, durable: bool = False
    ) -> None:
        self.name = name
        self.ref = ref  # set by the actor when it starts
        self.durable = durable

    def tell(self, message: Any) -> None:
        if self.ref is None:
            raise RegistrarUnavailableError(f"registrar {self.name!r} is still starting")
        try:
            self.ref.tell(message)
        except pykka.ActorDeadError as exc:
            raise DIRECTORY.gone_error(self.name) from exc

    def deliver(self, message: Any) -> None:
        if self.ref is None:
            raise RegistrarUnavailableError(f"registrar {self.name!r} is still starting")
        if self.durable and awaiting():  # (its commit, an fsync with durability="power",
            self.tell(message)  # would hold the loop: its own thread handles it)
            return
        try:
            deliver(self.ref, message)
        except pykka.ActorDeadError as exc:
            raise DIRECTORY.gone_error(self.name) from exc


class Directory:
    """Names of the registrars of this process, and the resolvers of those elsewhere."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._peers: dict[str, Peer] = {}
        self._gone: dict[str, str] = {}  # name -> "stopped" | "died"
        self._resolvers: tuple[Callable[[str], Peer | None], ...] = ()  # replaced, not changed
        self._namers: dict[Callable[[str], Peer | None], Callable[[], Iterable[str]]] = {}
        self._restart_expected: set[str] = set()  # a crash is not "gone for good"
        self._restarting: set[str] = set()  # down while their supervisor brings them back
        self._inherited: dict[str, int] = {}  # in a forked child: the parent's -> its pid

    def register(self, peer: Peer) -> None:
        """Publish a registrar under its name (`DuplicateNameError` if a living one has it)."""
        with self._lock:
            if peer.name in self._peers:
                raise DuplicateNameError(f"a registrar named {peer.name!r} is already running")
            self._peers[peer.name] = peer
            self._gone.pop(peer.name, None)
            self._inherited.pop(peer.name, None)
        MEMBERSHIP.back(peer.name)  # served here (again): no longer gone for good

    def unregister(self, peer: Peer, reason: str) -> None:
        """Withdraw a registrar; `reason` is `"stopped"` or `"died"`."""
        with self._lock:
            if self._peers.get(peer.name) is peer:
                del self._peers[peer.name]
                self._gone[peer.name] = reason

    def add_resolver(
        self,
        resolver: Callable[[str], Peer | None],
        names: Callable[[], Iterable[str]] | None = None,
    ) -> None:
        """Consult `resolver(name)` for names not registered here (`names()`: those it knows)."""
        with self._lock:
            self._resolvers = (*self._resolvers, resolver)
            if names is not None:
                self._namers[resolver] = names

    def remove_resolver(self, resolver: Callable[[str], Peer | None]) -> None:
        with self._lock:
            self._resolvers = tuple(r for r in self._resolvers if r != resolver)
            self._namers.pop(resolver, None)

    def names(self) -> set[str]:
        """Every registrar this process can reach now: its own, and those its resolvers name."""
        with self._lock:
            names = set(self._peers)
            namers = list(self._namers.values())
        for namer in namers:
            names.update(namer())
        return names

    def lookup(self, name: str) -> Peer:
        """The peer of registrar `name`, or the error `gone_error` gives."""
        peer = self._peers.get(name)  # a dict read is atomic; writers hold the lock
        if peer is not None:
            return peer
        for resolve in self._resolvers:  # (a tuple, replaced whole: read without the lock)
            found = resolve(name)
            if found is not None:
                return found
        raise self.gone_error(name)

    def gone_error(self, name: str) -> Exception:
        """The error for a registrar not reachable: `RegistrarUnavailableError` for a forked
        parent's or one being restarted, else `RegistrarStoppedError` (stopped),
        `RegistrarUnavailableError` (died) or `UnknownRegistrarError` (never seen)."""
        parent = self._inherited.get(name)
        if parent is not None:
            return RegistrarUnavailableError(
                f"registrar {name!r} runs in process {parent}, which this process was forked "
                f"from: a forked process has none of its parent's threads, so it cannot use "
                f"its parent's registrars; start a registrar in this process (it reaches "
                f"{name!r} by name if both processes joined one system)"
            )
        if name in self._restarting:
            return RegistrarUnavailableError(f"registrar {name!r} is being restarted")
        reason = self._gone.get(name)
        if reason == "stopped":
            return RegistrarStoppedError(f"registrar {name!r} was stopped", name)
        if reason == "died":
            return RegistrarUnavailableError(f"registrar {name!r} died")
        return UnknownRegistrarError(
            f"no registrar named {name!r}" + _known_names(name, self.names() - {name})
        )

    def local_peers(self) -> list[Peer]:
        with self._lock:
            return list(self._peers.values())

    # -- restarts: what a supervisor (or a test) says of a registrar's next end ------------

    def expect_restart(self, name: str, expected: bool = True) -> None:
        """Say whether a crash of registrar `name` will be followed by a restart (then its
        supervisor, not a death watch, decides)."""
        with self._lock:
            if expected:
                self._restart_expected.add(name)
            else:
                self._restart_expected.discard(name)

    def restart_expected(self, name: str) -> bool:
        return name in self._restart_expected

    def mark_restarting(self, names: Iterable[str], restarting: bool = True) -> None:
        """Say that registrars `names` are down for a restart (or no longer are): a message to one
        fails with `RegistrarUnavailableError`, even after a clean stop for the restart."""
        with self._lock:
            if restarting:
                self._restarting.update(names)
            else:
                self._restarting.difference_update(names)

    def forget_in_child(self, parent: int) -> None:
        """In a child forked from `parent`: this process's registrars are the parent's."""
        self._lock = runtime.Lock()  # a thread of the parent may have held it at the fork
        for name in self._peers:
            self._inherited[name] = parent
        self._peers.clear()
        self._restart_expected.clear()
        self._restarting.clear()


DIRECTORY = runtime.process_state(Directory(), Directory)


def _forget_in_child() -> None:
    DIRECTORY.forget_in_child(forkserver.forked_from() or 0)


forkserver.after_fork_in_child("the registrar directory", _forget_in_child)
