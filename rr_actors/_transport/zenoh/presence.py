"""The Zenoh carrier's presence: who serves what, as the liveliness tokens say.

```
 liveliness rr/<s>/live/**  ─► Presence._on_live (Zenoh's thread: queues, never blocks)
 Presence.ask(name) ─ liveliness get ─┘      │
                                             ▼
                        presence thread (SerialExecutor): _apply, in order
                          tables: process tokens, servers, claims, "stopped" marks,
                                  supervisors awaited
                                             │ then, outside the lock
                                             ▼
                  PresenceEvents (the member): process_gone, server_gone, lost, reachable
                     ─► fail waiting replies, close outboxes, peer_lost, peer_reachable
```

- a registrar's token (`live/reg/<name>/<zid>/<sup>/<limit>`) goes: every reply waiting
  on it fails with `RegistrarStoppedError` if its `stopped` mark came first (a clean stop
  declares the mark before it drops the token), else with `RegistrarUnavailableError`;
  later calls fail at once the same way;
- it is *lost for good* (the endpoints' `peer_lost`) when it did not stop cleanly and
  nobody restarts it: `<sup>` is `none`, or the process `<sup>` (its supervisor: the
  router process of a manager process that router started, `supervised_by`, or its own
  process when its `DIRECTORY.restart_expected`) has no token now or loses it later; a
  process that merely attached through the router publishes `none`;
- a registrar whose process token went (a cut link) and that comes back from the same
  process (same Zenoh id: a healed link, not a restart) is `peer_reachable`; the first
  message to that process waits (on its writer thread) until a ping of it is answered
  (`rr/<s>/ping/<zid>`, `outbox`): its token may be back before what is put to it
  gets through.

Claims (`live/claim/<name>/<zid>`) and `wait_turn` are `serve`'s half of "one name, one
server" (see `carrier`). `wait_turn` decides only from a full answer of the network (a
liveliness query that timed out answers with an error reply: it is asked again, and
`serve` fails with `RegistrarUnavailableError` if none comes within `CLAIM_TIMEOUT`).
"""

from __future__ import annotations

import collections
import functools
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import zenoh

from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.serial import SerialExecutor
from rr_actors._core.throttle import LogThrottle, short
from rr_actors._transport.zenoh.wire import Keys, NameAt
from rr_actors.errors import DuplicateNameError, RegistrarStoppedError, RegistrarUnavailableError

logger = logging.getLogger("rr_actors")

_DELETED_KEPT = 1024
"""Deletions remembered beyond which those older than every `ask` in flight are pruned."""

__all__ = [
    "ASK_PAUSE",
    "ASK_TIMEOUT",
    "CLAIM_TIMEOUT",
    "NO_WAITING",
    "Presence",
    "PresenceEvents",
    "Server",
]

ASK_TIMEOUT = 1.0
"""Seconds a miss of `resolve` (or `serve`'s check for the name) asks the network (never
on an actor's thread: there the name's writer thread asks, see `carrier`)."""
CLAIM_TIMEOUT = 5.0
"""Seconds `serve` waits for a rival claim of the same name to serve or withdraw, and for
the network to answer in full who serves the name (`Presence.wait_turn`)."""
ASK_PAUSE = 0.1
"""Seconds `wait_turn` waits before it asks again after a question that failed at once
(a timed-out one took `ASK_TIMEOUT` already); news of a token cuts it short."""

NO_WAITING = threading.local()
"""`active` on threads that must not wait on the network: the presence thread (what its
reports to the member run, `PresenceEvents`)."""


class Server:
    """A registrar of another process as its liveliness token says."""

    __slots__ = ("limit", "supervisor", "zid")

    def __init__(self, zid: str, supervisor: str, limit: int) -> None:
        self.zid = zid
        self.supervisor = supervisor
        self.limit = limit


class PresenceEvents(Protocol):
    """What `Presence` reports (on the presence thread, in order, outside its lock)."""

    def process_gone(self, zid: str) -> None:
        """Process `zid`'s token went: what was open to and from it ends."""

    def server_gone(self, name: str) -> None:
        """The last server of registrar `name` went: what waits on it fails."""

    def lost(self, name: str) -> None:
        """Registrar `name` is gone for good (nobody restarts it)."""

    def reachable(self, name: str) -> None:
        """Registrar `name` is back from the same process (a healed link)."""


class Presence:
    """The liveliness tables of one process's membership (written by its presence thread).

    Args:
        system: the system's name (for error messages).
        session: the open session.
        zid: this process's Zenoh id (its own tokens are left out).
        events: told what follows from a change (see `PresenceEvents`).
        on_token: called with a process's Zenoh id and whether its token came (`True`)
            or went, once `member` says so (on Zenoh's thread: it must not block).
    """

    def __init__(
        self,
        system: str,
        session: zenoh.Session,
        zid: str,
        events: PresenceEvents,
        *,
        on_token: Callable[[str, bool], None] | None = None,
    ) -> None:
        self._system = system
        self._session = session
        self._zid = zid
        self._events = events
        self._keys = Keys(system)
        self._changed = threading.Condition(threading.Lock())
        self._seq = 0
        self._deleted: dict[str, int] = {}  # token key -> seq of its last deletion
        self._asking: collections.Counter[int] = collections.Counter()  # asked_at -> asks
        self._procs: set[str] = set()
        self._vanished: set[str] = set()  # processes whose token went at least once
        self._servers: dict[str, dict[str, Server]] = {}
        self._claims: dict[str, set[str]] = {}
        self._stopped: set[NameAt] = set()
        self._gone: dict[str, str] = {}  # name -> "stopped" | "died"
        self._last: dict[str, str] = {}  # name -> the Zenoh id of its last server
        self._awaiting: dict[str, str] = {}  # name -> its supervisor: lost if that one goes
        self._members: set[str] = set()  # processes whose token is here (Zenoh's threads)
        self._on_token = on_token
        self._malformed = LogThrottle(logger)
        self._tokens: dict[str, Callable[[bool, str], list[Callable[[], None]] | None]] = {
            "proc": self._proc_token,  # each: the actions, or None for a malformed key
            "reg": self._reg_token,
            "claim": self._claim_token,
            "stopped": self._stopped_token,
        }
        self._queue = SerialExecutor("rr-zpresence")
        self._live = session.liveliness().declare_subscriber(
            self._keys.live(), self._on_live, history=True
        )

    # -- what the tables say -------------------------------------------------------------

    def serves(self, name: str) -> bool:
        """Whether another process serves `name` now."""
        return bool(self._servers.get(name))

    def server(self, name: str) -> Server | None:
        """A server of `name` in another process, if any."""
        servers = self._servers.get(name)
        if not servers:
            return None
        for server in list(servers.values()):
            return server
        return None

    def names(self) -> list[str]:
        """The registrars of other processes that serve now."""
        return sorted(name for name, servers in list(self._servers.items()) if servers)

    def gone(self, name: str) -> str | None:
        """How `name`'s last server went: "stopped", "died", or None (not gone)."""
        return self._gone.get(name)

    def unreachable(self, zid: str) -> bool:
        """Whether process `zid` went and is not back. (A process whose token was not seen
        yet is not: its message may overtake its token here.)"""
        return zid in self._vanished and zid not in self._procs

    def wait_serving(self, name: str, *, timeout: float) -> bool:
        """Whether another process serves `name` now or starts to within `timeout` seconds
        (woken by each applied event; False at the timeout or once closed)."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while not self._servers.get(name):
                left = deadline - time.monotonic()
                if left <= 0 or self._queue.closed:
                    return False
                self._changed.wait(left)
            return True

    def wait_turn(self, name: str) -> None:
        """With this process's claim on `name` declared: return once it may serve it.

        It decides from a full answer of the network only: a question about the name's
        tokens that timed out (a router too busy to answer within `ASK_TIMEOUT`) is asked
        again; an empty answer that is not known to be whole would let two processes
        that claim the name at once each see no rival, and both serve it.

        Raises:
            DuplicateNameError: another process serves it, or claims it and wins.
            RegistrarUnavailableError: the network did not answer in full within
                `CLAIM_TIMEOUT` seconds (whether another process serves it is unknown).
            RegistrarStoppedError: this process left the system meanwhile.
        """
        me = int(self._zid, 16)
        deadline = time.monotonic() + CLAIM_TIMEOUT
        while not self.ask(name):
            if self._queue.closed:
                raise RegistrarStoppedError("this process left the system")
            left = deadline - time.monotonic()
            if left <= 0:
                raise RegistrarUnavailableError(
                    f"cannot tell whether another process of system {self._system!r} serves "
                    f"a registrar named {name!r}: the network did not answer within "
                    f"{CLAIM_TIMEOUT:g} s, so this process does not serve it"
                )
            logger.debug("system %s: asking again who serves %s", self._system, name)
            with self._changed:  # (an answer that failed at once: a pause, cut short by news)
                self._changed.wait(min(left, ASK_PAUSE))
        with self._changed:
            while True:
                others = [z for z in self._servers.get(name, {}) if z != self._zid]
                if others:
                    raise DuplicateNameError(
                        f"a registrar named {name!r} is already served on system "
                        f"{self._system!r} (by process {others[0]})"
                    )
                rivals = [z for z in self._claims.get(name, ()) if z != self._zid]
                if any(int(z, 16) < me for z in rivals):
                    raise DuplicateNameError(
                        f"another process of system {self._system!r} starts a registrar "
                        f"named {name!r} at the same time, and wins the tie-break"
                    )
                if not rivals:
                    return
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DuplicateNameError(
                        f"another process of system {self._system!r} is starting a "
                        f"registrar named {name!r}"
                    )
                self._changed.wait(left)

    # -- hearing of tokens ---------------------------------------------------------------

    def _on_live(self, sample: zenoh.Sample) -> None:
        put, key = sample.kind == zenoh.SampleKind.PUT, str(sample.key_expr)
        zid = self._keys.parse_proc(key)  # (here, not on the presence thread: see `member`)
        if zid is not None:
            if put:
                self._members.add(zid)
            else:
                self._members.discard(zid)
            if self._on_token is not None:
                self._on_token(zid, put)
        self._queue.submit(functools.partial(self._apply, (put, key, None)))

    def member(self, zid: str) -> bool:
        """Whether process `zid`'s token is here now, as Zenoh's callbacks heard it.

        Updated on Zenoh's threads as the samples come (the presence thread applies them
        later: `unreachable` may lag). A process declares its token before it sends
        anything, but Zenoh sends declarations ahead of data: a frame may come before its
        sender's token, or after the token's end (`inbox.STRANGER_GRACE`).
        """
        return zid in self._members

    def ask(self, name: str) -> bool:
        """Ask the network for the tokens of `name` (bounded) and apply what it answers.

        An answer for a token whose deletion was seen after the question was asked is
        stale and left out.

        Returns:
            Whether the network answered in full: False if the question timed out (Zenoh
            then answers with an error reply, alongside what came in time) or failed, or
            was not asked (on a thread that must not wait: `NO_WAITING`).
        """
        if getattr(NO_WAITING, "active", False):
            return False  # (on Zenoh's or the presence thread: what the tables say must do)
        with self._changed:
            asked_at = self._seq
            self._asking[asked_at] += 1
        try:
            keys: list[str] = []
            whole = False
            try:
                replies = self._session.liveliness().get(
                    self._keys.live_of(name), timeout=ASK_TIMEOUT
                )
                whole = True
                for reply in replies:
                    if reply.ok is not None:
                        keys.append(str(reply.ok.key_expr))
                    else:  # ("Timeout": some answers may be missing)
                        whole = False
            except Exception as exc:  # noqa: BLE001 - a closed session, ...: not answered
                logger.debug("system %s: asking who serves %s failed: %s", self._system, name, exc)
                whole = False
            done = threading.Event()
            for key in keys:
                self._queue.submit(functools.partial(self._apply, (True, key, asked_at)))
            if not self._queue.submit(done.set):  # (closed: nothing will be applied)
                return False
            return done.wait(ASK_TIMEOUT) and whole
        finally:
            with self._changed:
                self._asking[asked_at] -= 1
                if self._asking[asked_at] <= 0:
                    del self._asking[asked_at]

    def close(self) -> None:
        """Stop applying events (and waking `wait_serving`)."""
        self._queue.close(timeout=0)
        with self._changed:
            self._changed.notify_all()

    # -- the presence thread -------------------------------------------------------------

    def _apply(self, item: tuple[bool, str, Any]) -> None:
        """Apply one liveliness event (the presence thread): tables, then what follows."""
        NO_WAITING.active = True
        put, key, extra = item
        with self._changed:
            self._seq += 1
            if put and extra is not None and self._deleted.get(key, -1) > extra:
                return  # a stale answer of `ask`
            if not put:
                self._deleted[key] = self._seq
                if len(self._deleted) > _DELETED_KEPT:  # (only an `ask` in flight needs them)
                    oldest = min(self._asking, default=self._seq)
                    self._deleted = {k: q for k, q in self._deleted.items() if q > oldest}
            actions = self._change(put, key)
            self._changed.notify_all()
        for action in actions:
            try:  # (one failing action must not keep the others from running)
                action()
            except Exception:
                logger.exception("presence: %s after %s failed", action, key)

    def _change(self, put: bool, key: str) -> list[Callable[[], None]]:
        """Apply one event to the tables (holding the lock); what to do after.

        A malformed key (a buggy member's token) is ignored with a rate-limited WARNING.
        """
        token = self._tokens.get(self._keys.kind(key))
        if token is None:
            return []  # (a kind of token a later version may add)
        actions = token(put, key)
        if actions is None:
            self._malformed.warning(
                "system %s: ignored a malformed liveliness token %s (declared by a buggy "
                "member? see _transport/zenoh/wire.py for the key expressions)",
                self._system,
                short(key),
            )
            return []
        return actions

    def _proc_token(self, put: bool, key: str) -> list[Callable[[], None]] | None:
        zid = self._keys.parse_proc(key)
        if zid is None:
            return None
        return [] if zid == self._zid else self._process_event(put, zid)

    def _reg_token(self, put: bool, key: str) -> list[Callable[[], None]] | None:
        server = self._keys.parse_server(key)
        if server is None:
            return None
        if server.zid == self._zid:
            return []
        return self._server_event(
            put, server.name, Server(server.zid, server.supervisor, server.limit)
        )

    def _claim_token(self, put: bool, key: str) -> list[Callable[[], None]] | None:
        claim = self._keys.parse_claim(key)
        if claim is None:
            return None
        claims = self._claims.setdefault(claim.name, set())
        if put:
            claims.add(claim.zid)
        else:
            claims.discard(claim.zid)
        return []

    def _stopped_token(self, put: bool, key: str) -> list[Callable[[], None]] | None:
        mark = self._keys.parse_stopped(key)
        if mark is None:
            return None
        if put:
            self._stopped.add(mark)
        else:
            self._stopped.discard(mark)
        return []

    def _process_event(self, put: bool, zid: str) -> list[Callable[[], None]]:
        """Process `zid`'s token came or went: registrars it supervised are lost now."""
        if put:
            self._procs.add(zid)
            return []
        self._procs.discard(zid)
        self._vanished.add(zid)
        lost = [name for name, supervisor in self._awaiting.items() if supervisor == zid]
        for name in lost:
            del self._awaiting[name]
        actions: list[Callable[[], None]] = [functools.partial(self._events.lost, n) for n in lost]
        actions.append(functools.partial(self._events.process_gone, zid))
        return actions

    def _server_event(self, put: bool, name: str, server: Server) -> list[Callable[[], None]]:
        """A server's token of registrar `name` came or went."""
        servers = self._servers.setdefault(name, {})
        zid = server.zid
        if put:
            if zid in servers:
                return []
            replaced: list[Callable[[], None]] = []
            if servers:  # a restart seen before its predecessor's token went (one name,
                # one server): that one died; what waits on it fails now, not at its
                # timeout (its token's end, when it comes, finds it gone already)
                self._last[name] = next(iter(servers))
                servers.clear()
                replaced.append(functools.partial(self._events.server_gone, name))
            servers[zid] = server
            self._gone.pop(name, None)
            MEMBERSHIP.back(name)  # served (again): no longer gone for good
            self._awaiting.pop(name, None)
            if self._last.get(name) == zid and zid in self._vanished:
                return [functools.partial(self._events.reachable, name)]  # a healed link
            return replaced
        if servers.pop(zid, None) is None or servers:
            return []  # unknown, or a rival that yielded: another one serves
        stopped = NameAt(name, zid) in self._stopped
        self._gone[name] = "stopped" if stopped else "died"
        self._last[name] = zid
        actions: list[Callable[[], None]] = [functools.partial(self._events.server_gone, name)]
        if stopped:
            return actions
        supervisor = server.supervisor
        if supervisor == "none" or (supervisor != self._zid and supervisor not in self._procs):
            actions.append(functools.partial(self._events.lost, name))
        else:
            self._awaiting[name] = supervisor  # lost if its supervisor goes too
        return actions
