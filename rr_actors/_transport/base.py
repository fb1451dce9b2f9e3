"""The carrier interface: how registrars of different processes (or hosts) reach each other.

A registrar talks to other registrars only through the directory
(`rr_actors._core.directory`): it looks a name up and `tell`s the `Peer` it gets a
message (`Load`, `Unload`, `StatusNotice`, ...); a message that wants an answer carries a
`Reply`. A process's membership of a system (its `Transport`: a messenger over one
carrier, `messenger.py`) makes names of other processes resolvable and moves the
messages:

```
 process A                                          process B
 registrar ──lookup(name)──► Directory ──resolve──► Transport.resolve(name) -> Peer
    │                                                 (carrier.knows, carrier.peer)
    └── peer.tell(message) ── bytes / samples ──► the carrier delivers to the registrar
                                                      (DIRECTORY.lookup(name).tell(message))
    reply.set_result/set_error ◄──── the answer ◄──── the message's stand-in reply
```

The contract every carrier keeps, and how a carrier answers for a process lost for good
(rule 19): `Transport`'s docstring.

Carriers: `unix/` (AF_UNIX sockets in a private runtime directory, authenticated with a
per-system key) and `zenoh/` (`zenoh/net.py`'s `ZenohNetwork`, `zenoh/carrier.py`: Eclipse Zenoh
across hosts, presence by liveliness tokens). Each gives a `Messenger` (which is the
`Transport`) its `Carrier` (`messenger.py`: a route per registrar reached, a listening
per registrar served, answers back, liveliness reports) and an `Address`, and needs no
change in the registrar.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from rr_actors._core.directory import Peer, Reply

__all__ = ["Address", "Endpoint", "Peer", "Transport"]


class Endpoint(Protocol):
    """A registrar of this process, as a carrier serves it."""

    @property
    def name(self) -> str:
        """The registrar's name."""
        ...

    @property
    def max_message_bytes(self) -> int:
        """The largest message (pickled, in bytes) it takes from another process, or
        answers with; larger ones get `MessageTooLargeError` (the sender before it sends)."""
        ...

    def run(self, fn: Callable[[Any], Any]) -> Any:
        """Run `fn(registrar)` on the calling thread and return what it returns."""
        ...

    def wait_ended(self, timeout: float | None = None) -> bool:
        """Block until the registrar ended (stopped or died); whether it did."""
        ...

    def stopped_cleanly(self) -> bool:
        """Whether it ended because its owner stopped it (not a crash)."""
        ...

    def listening(self) -> None:
        """Called once the carrier serves it: the other processes can reach it from now on.

        It must return at once (the carrier's `serve` calls it).
        """
        ...

    def peer_lost(self, name: str) -> None:
        """Registrar `name` of another process is gone and nobody will restart it (rule
        19: its process ended and no supervisor started it, or its supervisor is
        gone or unreachable too). The registrar releases the ids `name` held here and
        reports the ids it held at `name` `FATAL` (its status callbacks, and up their
        dependents), then forgets them; the death watch's `ConsumerDown` does the same.

        Called on a carrier thread; returns at once. Calling it twice is harmless.
        """
        ...

    def peer_reachable(self, name: str) -> None:
        """Registrar `name` of another process can be reached again after it could not be
        (a healed link, not a restart: a restarted registrar reconciles by itself). The
        registrar reconciles with it (rule 20): as a consumer it retries its `Reconcile`
        (backoff up to 2 s, or when one is unanswered for `call_timeout`) until it is
        answered, `name` is lost or stopped, or the registrar stops.

        Called on a carrier thread; returns at once.
        """
        ...

    def yield_name(self, reason: str) -> None:
        """Another process serves this registrar's name too, and the carrier keeps that
        one (rule 22: after a healed link, the one served first). The carrier has
        stopped serving this one already; the registrar unloads every resource it serves
        (its consumers' ids are released without a word: they reconcile with the one
        kept, which reports `FATAL` the ids it does not hold) and then stops.

        Called on a carrier thread; returns at once. `reason` says why (for its log).
        """
        ...

    def keep_name(self, reply: Reply) -> None:
        """The one kept in its place went for good while this one yields (rule 22): if it
        has not begun to stop, it serves its name again once what it unloads is gone, and
        `reply` gets `True` (the carrier then serves it again); `False` if it is not
        yielding or began to stop.

        Called on a carrier thread; returns at once.
        """
        ...


class Address(Protocol):
    """How another process joins the same system: it pickles; `attach()` joins there."""

    def attach(self) -> Transport:
        """Join the system from this process (idempotent per process)."""
        ...


class Transport(Protocol):
    """One process's membership of a system of registrars, over one carrier.

    The contract every carrier keeps (the transport tests check it for each one):

    - **open a channel**: `resolve(name)` returns a `Peer` for a registrar served by another
      process of the system, or `None` if the carrier does not know the name;
    - **send**: `Peer.tell(message)` never blocks on the other process; messages told to one
      peer from one process arrive in the order they were told; a message that does not
      pickle raises `ConfigError` at the sender and nothing is sent; nor is one larger than
      the receiving registrar's `max_message_bytes` (`MessageTooLargeError`, a `ConfigError`);
    - **size**: each connection is bounded by the `max_message_bytes` of the registrar it
      leads to, both ways: the receiver skips a larger frame unread (answering the error),
      and a larger answer becomes that error (its `compensation()` runs);
    - **receive**: `serve(endpoint)` makes a registrar of this process reachable; what arrives
      for it is told to it through the directory, with a stand-in reply that sends the
      answer back; a stand-in whose answer cannot be pickled sends an error instead, and one
      whose answer cannot reach the sender hands the message's `compensation()` to the
      registrar (`rr_actors._core.wire`);
    - **liveness ("peer gone")**: when the other process dies or its registrar stops, every
      reply still waiting on it fails at once with `RegistrarUnavailableError` (or
      `RegistrarStoppedError` after a clean stop), never by waiting out a timeout; a later
      `tell` to a name that is served again (a restarted manager) reaches the new server;
    - **control**: `run(name, fn, timeout=)` runs `fn(registrar)` where that registrar lives;
    - **lost for good (rule 19)**: when a registrar of another process is gone and
      nobody will restart it, every registrar of the system hears so, at least once: from
      the death watch (`ConsumerDown`, which whoever started it, a supervisor that gave up
      or the owner of an unsupervised manager process, tells every name `names()` lists),
      or from the carrier, which calls `Endpoint.peer_lost` with the name on every registrar it
      serves when the one who would say so is gone too (a host lost with its supervisor).
      Its consumers then report `FATAL` for the ids they held there and forget them (one
      that hears it while another registrar of the name serves, rule 22's kept one,
      reconciles with that one first: what it holds stays held). A
      carrier never calls `peer_lost` for a registrar whose supervisor is alive: that one
      restarts it, and its restored catalog keeps its consumers' ids (rule 15), or it
      sends the death watch if it gives up. Only a process that `Transport.supervised_by`
      names (a manager process's supervisor) or, while `DIRECTORY.restart_expected(name)`,
      its own process speaks for it; a process that merely joined the system has nobody.
      Each carrier says who that is: Zenoh in the registrar's liveliness token, AF_UNIX in
      `<runtime_dir>/<name>.restart` (`unix/system.py` says how, and its limits);
    - **presence**: `Endpoint.peer_reachable(name)` when a registrar that could not be
      reached answers again (a healed link, not a restart); the consumer side retries its
      `Reconcile` until it is answered; `names()` lists the registrars it can reach;
    - **one name, one registrar (rule 22)**: `serve` refuses a name another process serves
      (`DuplicateNameError`), and, where the carrier cannot hear the rest of the system, one
      it cannot tell is free (`RegistrarUnavailableError`). A carrier that can see two
      servers of one name (Zenoh, after a healed link) keeps one by a rule every process
      applies alike, calls `Endpoint.yield_name` on the other, and tells `peer_reachable`
      to the consumers of the one that yielded;
    - **health**: `serving_trouble(name)` says for how long a registrar served here has been
      unable to take new connections (a listener out of file descriptors keeps trying);
    - **join**: `address` pickles; `address.attach()` in another process joins the system.

    Low-level errors (`EOFError`, `BrokenPipeError`, `OSError`, pickling errors) never reach
    a caller: a carrier translates them into rr_actors errors with `raise ... from exc`.

    A carrier with a lease (Zenoh) counts a process silent for longer than it (frozen, or
    behind a cut link) as gone: its replies fail with `RegistrarUnavailableError` then.
    """

    @property
    def address(self) -> Address:
        """What to hand to processes that should join the same system."""
        ...

    @property
    def closed(self) -> bool:
        """Whether this process left the system."""
        ...

    def resolve(self, name: str) -> Peer | None:
        """A channel to registrar `name` of another process, or `None` if unknown here."""
        ...

    def names(self) -> list[str]:
        """The registrars of other processes of the system that can be reached now (any
        host): for the death watch and a restarted provider's reconciliation."""
        ...

    def serve(self, endpoint: Endpoint) -> None:
        """Make a registrar of this process reachable; stops by itself when it ends.

        Raises:
            DuplicateNameError: another process of the system serves that name.
            ConfigError: the carrier cannot serve it (a bad name or address).
            RegistrarUnavailableError: the carrier cannot tell in time whether another
                process serves it (a network that did not answer).
            RegistrarStoppedError: this process left the system.
        """
        ...

    def run(self, name: str, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """Run `fn(registrar)` where registrar `name` lives; return what it returns.

        Raises:
            UnknownServerError: nobody serves that name on the system.
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: its process died or cannot be reached.
            RegistrarStoppedError: it was stopped.
        """
        ...

    def serving_trouble(self, name: str) -> tuple[float, str] | None:
        """For how long (seconds) and why registrar `name`, served here, has been unable to
        take new connections; `None` if it can, or if it is not served here."""
        ...

    def supervised_by(self, pid: int | None) -> None:
        """Say that process `pid` speaks for the registrars this process serves from now on
        when this process dies (rule 19): it restarts them or sends their death watch (a
        manager process's supervisor, or the owner of a `RemoteRegistrar`; the manager
        process says so, `_process/child.py`); `None`: nobody. Until then nobody does,
        except for a registrar with `DIRECTORY.restart_expected(name)` (its own process)."""
        ...

    def close(self) -> None:
        """Leave the system: stop serving, fail what waits (idempotent)."""
        ...
