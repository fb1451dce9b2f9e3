"""Where registrars find each other by name, and what a message is sent through.

A *peer* is anything with `tell(message)`: a registrar actor in this process, or (with
manager processes) a channel to a registrar in another process. The directory maps names
to peers, remembers why a name went away (stopped or died, so callers get the right
error: and a registrar that its supervisor is bringing back is neither, it is
unavailable for now). Who is gone for good is the membership's (`membership.py`).

In a child forked from this process, the parent's registrars are not the child's: the
directory forgets them at the fork (`rr_actors._platform.fork`), and a handle of one used
in the child gets a `RegistrarUnavailableError` that says so. The resolvers stay: a
carrier the parent joined is the child's too (the carrier resets its own state).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any, Protocol

import pykka

from rr_actors._core import runtime
from rr_actors._core.actor import awaiting, deliver
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._platform import fork
from rr_actors.errors import (
    DuplicateNameError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownRegistrarError,
    _known_names,
)

__all__ = ["DIRECTORY", "Directory", "LocalPeer", "Peer", "Reply"]

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
        """`tell`, from a carrier's receiving thread (which holds no lock), or an event
        loop's thread stepping an awaited call: a registrar of this process that is idle
        may handle it on that thread (`_core/actor.py`'s turn); from a loop, not a
        durable one (`LocalPeer`)."""


class LocalPeer:
    """A registrar actor in this process.

    Args:
        name: the registrar's name.
        ref: its actor (`None`: set by the actor when it starts).
        durable: its steps write to disk before they answer (a backup with
            `save_on_modify`): an event loop's thread never takes its turn (`deliver`).
    """

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
    """Names of the registrars of this process (and, later, of its system)."""

    def __init__(self) -> None:
        self._lock = runtime.Lock()
        self._peers: dict[str, Peer] = {}
        self._gone: dict[str, str] = {}  # name -> "stopped" | "died"
        self._resolvers: tuple[Callable[[str], Peer | None], ...] = ()  # replaced, not changed
        self._namers: dict[Callable[[str], Peer | None], Callable[[], Iterable[str]]] = {}
        self._restart_expected: set[str] = set()  # a crash is not "gone for good"
        self._restarting: set[str] = set()
        """Names of registrars that are down while their supervisor brings them back:
        stopped (a group restart stops the crashed child's siblings) or crashed, a
        caller gets `RegistrarUnavailableError` (retry), not `RegistrarStoppedError`."""
        self._inherited: dict[str, int] = {}  # in a forked child: the parent's -> its pid

    def register(self, peer: Peer) -> None:
        """Publish a registrar under its name.

        Raises:
            DuplicateNameError: a living registrar already has that name.
        """
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
        """Consult `resolver(name)` for names not registered in this process.

        `names()`, if given, lists the names it knows, for the message of an unknown name.
        """
        with self._lock:
            self._resolvers = (*self._resolvers, resolver)
            if names is not None:
                self._namers[resolver] = names

    def remove_resolver(self, resolver: Callable[[str], Peer | None]) -> None:
        """Stop consulting `resolver` (no-op if it was not added)."""
        with self._lock:
            self._resolvers = tuple(r for r in self._resolvers if r != resolver)
            self._namers.pop(resolver, None)

    def names(self) -> set[str]:
        """Every registrar this process can reach now: its own, and those its resolvers name.

        (A provider that starts tells them all to reconcile: rule 20.)
        """
        with self._lock:
            names = set(self._peers)
            namers = list(self._namers.values())
        for namer in namers:
            names.update(namer())
        return names

    def lookup(self, name: str) -> Peer:
        """Return the peer of registrar `name`.

        Raises:
            UnknownRegistrarError: no registrar of that name was ever seen.
            RegistrarStoppedError: it was stopped for good.
            RegistrarUnavailableError: it died, or is being restarted.
        """
        peer = self._peers.get(name)  # a dict read is atomic; writers hold the lock
        if peer is not None:
            return peer
        for resolve in self._resolvers:  # (a tuple, replaced whole: read without the lock)
            found = resolve(name)
            if found is not None:
                return found
        raise self.gone_error(name)

    def gone_error(self, name: str) -> Exception:
        """The error for a registrar that is not (or no longer) reachable.

        In a forked child, `RegistrarUnavailableError` naming the parent for a registrar
        of the parent's. `RegistrarUnavailableError` while its supervisor restarts it
        (`restarting`), even if it was stopped for the restart; else
        `RegistrarStoppedError` if it was stopped, `RegistrarUnavailableError` if it died,
        `UnknownRegistrarError` if never seen.
        """
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
            return RegistrarStoppedError(f"registrar {name!r} was stopped")
        if reason == "died":
            return RegistrarUnavailableError(f"registrar {name!r} died")
        return UnknownRegistrarError(
            f"no registrar named {name!r}" + _known_names(name, self.names() - {name})
        )

    def local_peers(self) -> list[Peer]:
        """Every registrar registered in this process."""
        with self._lock:
            return list(self._peers.values())

    # -- restarts: what a supervisor (or a test) says of a registrar's next end ------------

    def expect_restart(self, name: str, expected: bool = True) -> None:
        """Say whether a crash of registrar `name` will be followed by a restart.

        While one is expected, its crash is not a consumer gone for good: no death watch
        (`broadcast`) from the registrar itself; its supervisor decides.
        """
        with self._lock:
            if expected:
                self._restart_expected.add(name)
            else:
                self._restart_expected.discard(name)

    def restart_expected(self, name: str) -> bool:
        """Whether a crash of registrar `name` will be followed by a restart."""
        return name in self._restart_expected

    def mark_restarting(self, names: Iterable[str], restarting: bool = True) -> None:
        """Say that registrars `names` are down for a restart (or no longer are).

        While they are, a message to one of them fails with `RegistrarUnavailableError`
        (retry), not `RegistrarStoppedError`, even after a clean stop for the restart.
        """
        with self._lock:
            if restarting:
                self._restarting.update(names)
            else:
                self._restarting.difference_update(names)

    def broadcast(self, message: object, *, also: Iterable[str] = (), skip: str = "") -> None:
        """Tell `message` to every registrar of this process and to those named in `also`.

        A restart that lost ids (`ReconcileAsk`) reaches everyone who may hold them this
        way. Registrar `skip` is left out; one that cannot be reached is skipped
        (logged at debug level).
        """
        targets = {peer.name for peer in self.local_peers()} | set(also)
        targets.discard(skip)
        for target in sorted(targets):
            try:
                self.lookup(target).tell(message)
            except RrError:
                logger.debug("%s: registrar %s unreachable", type(message).__name__, target)

    def forget_in_child(self, parent: int) -> None:
        """In a child forked from process `parent`: the registrars of this process are
        the parent's (their actors have no thread here); nothing restarts here either."""
        self._lock = runtime.Lock()  # a thread of the parent may have held it at the fork
        for name in self._peers:
            self._inherited[name] = parent
        self._peers.clear()
        self._restart_expected.clear()
        self._restarting.clear()


DIRECTORY = runtime.process_state(Directory(), Directory)


def _forget_in_child() -> None:
    DIRECTORY.forget_in_child(fork.forked_from() or 0)


fork.after_fork_in_child("the registrar directory", _forget_in_child)
