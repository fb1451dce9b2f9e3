"""The Zenoh carrier's presence: who serves what, as the liveliness tokens say.

Who is gone, lost for good (rule 19), reachable again (rule 20); two servers of one name
(rule 22). How and why: docs/explanation/inside.md ("Zenoh presence").
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

from rr_actors._core.hlc import CLOCK
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.serial import SerialExecutor
from rr_actors._core.throttle import LogThrottle, short
from rr_actors._transport.messenger import Messenger, when
from rr_actors._transport.resolve import FIRST_SERVED, Resolution
from rr_actors._transport.zenoh import callbacks
from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.wire import HostKey, Keys, NameAt, ServerKey
from rr_actors.errors import DuplicateNameError, RegistrarStoppedError, RegistrarUnavailableError

logger = logging.getLogger("rr_actors")

_DELETED_KEPT = 1024  # deletions remembered beyond which those no question needs go

ASK_TIMEOUT = 1.0
"""Seconds a question to the network waits (never on an actor's thread)."""
CLAIM_TIMEOUT = 5.0
"""Seconds `wait_turn` waits for a rival claim to serve or withdraw, and for a full answer."""
EMPTY_BELIEVED = 0.25
"""Seconds an empty answer about a name never heard to go is asked again before it is
believed (`question_until_seen`): a client's liveliness query can come back empty at
once while its router holds a matching token (Zenoh 1.x)."""
EMPTY_PAUSE = 0.005
"""Seconds between two questions of `question_until_seen`."""
ASK_PAUSE = 0.1
"""Seconds `wait_turn` waits before asking again after a question that failed at once."""

NO_WAITING = threading.local()
"""`active` on threads that must not wait on the network (the presence thread)."""


Server = ServerKey  # a registrar of another process as its liveliness token says (`Sided`)


class PresenceEvents(Protocol):
    """What `Presence` reports to its carrier (the presence thread, in order, unlocked)."""

    def process_gone(self, zid: str) -> None: ...  # what was open to and from it ends
    def server_gone(self, name: str) -> None: ...  # the last one went: what waits fails
    def served_elsewhere(self, name: str, server: Server) -> None: ...  # (rule 22)


class Presence:
    """The liveliness tables of one process's membership (written by its presence thread).
    `on_token` runs on Zenoh's thread (never blocks); `router` is `None` if this is one."""

    def __init__(
        self,
        system: str,
        session: zenoh.Session,
        zid: str,
        events: PresenceEvents,
        *,
        hearer: Messenger,
        on_token: Callable[[str, bool], None] | None = None,
        router: str | None = None,
        resolution: Resolution = FIRST_SERVED,
        on_hosts: Callable[[int], None] | None = None,
    ) -> None:
        self._system = system
        self._resolution = resolution
        self._on_hosts = on_hosts
        self._host_keys: set[HostKey] = set()  # the host tokens here (one per host's router)
        self._most = 0  # the most hosts heard at once, here or by a router heard
        self._router = router
        self._session = session
        self._zid = zid
        self._events = events
        self._hearer = hearer
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
        self._conflicts: set[tuple[str, str, int]] = set()  # (name, zid, stamp) warned of
        self._mine: dict[str, ServerKey] = {}  # name -> its token: served by this process
        self._members: set[str] = set()  # processes whose token is here (Zenoh's threads)
        self._on_token = on_token
        self._malformed = LogThrottle(logger)
        self._tokens: dict[str, Callable[[bool, str], list[Callable[[], None]] | None]] = {
            "proc": self._proc_token,  # each: the actions, or None for a malformed key
            "reg": self._reg_token,
            "claim": self._claim_token,
            "host": self._host_token,
            "stopped": self._stopped_token,
        }
        self._queue = SerialExecutor("rr-zpresence")
        callbacks.worker(session, self._queue)  # (its reports may call Zenoh)
        self._live = session.liveliness().declare_subscriber(
            self._keys.live(), tracked(session, self._on_live), history=True
        )

    # -- what the tables say -------------------------------------------------------------

    def serves(self, name: str) -> bool:
        """Whether another process serves `name` now."""
        return bool(self._servers.get(name))

    def server(self, name: str) -> Server | None:
        """The server of `name` in another process that rule 22 keeps, if any."""
        servers = self._servers.get(name)
        if not servers:
            return None
        return self._resolution.kept(name, list(servers.values()))

    def hosts(self) -> int:
        """How many hosts this process hears now (their routers' host tokens)."""
        return len({host.zid for host in list(self._host_keys)})

    def most(self, router: str | None) -> int:
        """The most hosts heard at once, here or by a router heard; 0 until known."""
        if router is not None and all(host.zid != router for host in list(self._host_keys)):
            return 0
        return self._most

    def names(self) -> list[str]:
        return sorted(name for name, servers in list(self._servers.items()) if servers)

    def gone(self, name: str) -> str | None:
        """How `name`'s last server went: "stopped", "died", or None (not gone)."""
        return self._gone.get(name)

    def unreachable(self, zid: str) -> bool:
        """Whether process `zid` went and is not back (one never seen is not)."""
        return zid in self._vanished and zid not in self._procs

    def wait_serving(self, name: str, *, timeout: float) -> bool:
        """Whether another process serves `name` within `timeout` seconds."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while not self._servers.get(name):
                left = deadline - time.monotonic()
                if left <= 0 or self._queue.closed:
                    return False
                self._changed.wait(left)
            return True

    def wait_turn(self, name: str) -> None:
        """Return once this claim may serve `name` (inside.md, "When a claim may serve").

        Raises `DuplicateNameError`, `RegistrarUnavailableError` (no full answer within
        `CLAIM_TIMEOUT` s, or a supervisor may restart it), `RegistrarStoppedError`.
        """
        me = int(self._zid, 16)
        deadline = time.monotonic() + CLAIM_TIMEOUT
        while (why := self.question(name)) is not None:
            if self._queue.closed:
                raise RegistrarStoppedError("this process left the system")
            left = deadline - time.monotonic()
            orphan = self._router is not None and self.unreachable(self._router)
            if left <= 0 or orphan:  # (its router's token went: no use asking again)
                raise RegistrarUnavailableError(
                    f"cannot tell whether another process of system {self._system!r} serves "
                    f"a registrar named {name!r}, so this process does not serve it: {why}"
                    + ("" if orphan else f" (asked for {CLAIM_TIMEOUT:g} s)")
                )
            logger.debug("system %s: asking again who serves %s (%s)", self._system, name, why)
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
                self._refuse_awaited(name)
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

    def _refuse_awaited(self, name: str) -> None:
        """Raise if `name`'s last server died and its supervisor may restart it (hold lock)."""
        supervisor = self._awaiting.get(name)
        if supervisor is None or MEMBERSHIP.gone().get(name) is not None:
            return
        raise RegistrarUnavailableError(
            f"registrar {name!r} of system {self._system!r} was served by process "
            f"{self._last.get(name, '?')}, which went without a clean stop, and its "
            f"supervisor (process {supervisor}) may restart it: it is not lost (rule 19), "
            f"so this process does not serve that name until it is served again or lost "
            f"(rule 22)"
        )

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
        """Whether process `zid`'s token is here now, as Zenoh's callbacks heard it."""
        return zid in self._members

    def question_until_seen(self, name: str) -> str | None:
        """`question`, asked again for `EMPTY_BELIEVED` s while no server of `name` is named."""
        deadline = time.monotonic() + EMPTY_BELIEVED
        pause = threading.Event()
        why = self.question(name)
        while (
            why is None
            and not self.serves(name)
            and self.gone(name) is None
            and time.monotonic() < deadline
        ):
            pause.wait(EMPTY_PAUSE)
            why = self.question(name)
        return why

    def question(self, name: str) -> str | None:
        """Ask for the tokens of `name` and apply them; `None` if answered in full, else why."""
        if getattr(NO_WAITING, "active", False):
            return "not asked on this thread"  # (Zenoh's or the presence thread's)
        with self._changed:
            asked_at = self._seq
            self._asking[asked_at] += 1
        try:
            keys: list[str] = []
            why: str | None = None
            try:
                with callbacks.calling(self._session):  # (a caller's thread, often)
                    replies = self._session.liveliness().get(
                        self._keys.live_of(name), timeout=ASK_TIMEOUT
                    )
                    for reply in replies:
                        if reply.ok is not None:
                            keys.append(str(reply.ok.key_expr))
                        else:  # ("Timeout": some answers may be missing)
                            why = f"the network did not answer within {ASK_TIMEOUT:g} s"
            except Exception as exc:  # noqa: BLE001 - a closed session, ...: not answered
                logger.debug("system %s: asking who serves %s failed: %s", self._system, name, exc)
                why = f"the question failed ({exc})"
            if why is None and not self._router_answers():
                why = (
                    f"this process's router (process {self._router}) does not answer: this "
                    f"process has no link to the rest of the system and hears nothing of it"
                )
            done = threading.Event()
            for key in keys:
                self._queue.submit(functools.partial(self._apply, (True, key, asked_at)))
            if not self._queue.submit(done.set):  # (closed: nothing will be applied)
                return "this process left the system"
            if not done.wait(ASK_TIMEOUT):
                return "this process's presence thread is late"
            return why
        finally:
            with self._changed:
                self._asking[asked_at] -= 1
                if self._asking[asked_at] <= 0:
                    del self._asking[asked_at]

    def _router_answers(self) -> bool:
        """Whether this process's router answers a ping."""
        if self._router is None:
            return True
        try:
            with callbacks.calling(self._session):
                replies = self._session.get(self._keys.ping(self._router), timeout=ASK_TIMEOUT)
                return any(reply.ok is not None for reply in replies)
        except Exception as exc:  # noqa: BLE001 - a closed session: no answer
            logger.debug("system %s: pinging the router failed: %s", self._system, exc)
            return False

    def close(self) -> None:
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
        """Apply one event to the tables (holding the lock); what to do after."""
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
        if put:  # (a registration heard of comes before any made here from now on)
            CLOCK.receive(server.stamp)
        if server.zid == self._zid:  # (this process's own: not a server "elsewhere")
            if put:
                self._mine[server.name] = server
            elif self._mine.get(server.name) == server:
                del self._mine[server.name]
            return []
        return self._server_event(put, server.name, server)

    def _host_token(self, put: bool, key: str) -> list[Callable[[], None]] | None:
        host = self._keys.parse_host(key)
        if host is None:
            return None
        if not put:
            self._host_keys.discard(host)
            return []
        before = self._most
        self._host_keys.add(host)
        self._most = max(self._most, host.most, self.hosts())
        if self._most > before and self._on_hosts is not None:
            return [functools.partial(self._on_hosts, self._most)]
        return []

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
        if zid == self._router:
            logger.warning(
                "system %s: this process lost its link to its router (process %s): it "
                "hears nothing of the rest of the system, and serves no registrar from now "
                "on (rule 22)",
                self._system,
                zid,
            )
        lost = [name for name, supervisor in self._awaiting.items() if supervisor == zid]
        for name in lost:
            del self._awaiting[name]
        actions: list[Callable[[], None]] = [functools.partial(self._hearer.lost, n) for n in lost]
        actions.append(functools.partial(self._events.process_gone, zid))
        return actions

    def _server_event(self, put: bool, name: str, server: Server) -> list[Callable[[], None]]:
        servers = self._servers.setdefault(name, {})
        zid = server.zid
        if not put:
            return self._server_went(name, server)
        known = servers.get(zid)
        if known is not None and known.stamp == server.stamp:
            return []
        if any(self._follows(other, server) for other in servers.values()):
            return []  # a predecessor's late news (an answer of `ask`): it died
        dead = [z for z, other in servers.items() if self._follows(server, other)]
        actions: list[Callable[[], None]] = []
        if dead:  # a restart seen before its predecessor's token went: that one died
            self._last[name] = dead[-1]
            for gone in dead:
                del servers[gone]
            actions.append(functools.partial(self._events.server_gone, name))
        mine = self._mine.get(name)
        if servers or mine is not None:
            here = [] if mine is None else [mine]
            self._two_servers(name, [*here, *servers.values(), server])
        servers[zid] = server
        self._gone.pop(name, None)
        MEMBERSHIP.back(name)  # served (again): no longer gone for good
        self._awaiting.pop(name, None)
        actions.append(functools.partial(self._events.served_elsewhere, name, server))
        if self._last.get(name) == zid and zid in self._vanished:
            actions.append(functools.partial(self._hearer.reachable, name))  # a healed link
        return actions

    @staticmethod
    def _follows(server: Server, other: Server) -> bool:
        """Whether `server` is a restart of `other`: same process or supervisor, later stamp."""
        same = server.zid == other.zid or (
            server.supervisor != "none" and server.supervisor == other.supervisor
        )
        return same and server.stamp > other.stamp

    def _two_servers(self, name: str, servers: list[Server]) -> None:
        """Two processes serve `name` (rule 22): a WARNING once per pair."""
        winner = self._resolution.kept(name, servers)
        assert winner is not None
        for other in servers:
            mark = (name, other.zid, other.stamp)
            if other is winner or other.zid == self._zid or mark in self._conflicts:
                continue  # (this process's own yields: it says so at ERROR)
            self._conflicts.add(mark)
            logger.warning(
                "system %s: two processes serve registrar %s (after a healed link): %s, "
                "since %s, is kept; %s, since %s, yields (rule 22)",
                self._system,
                name,
                winner.zid,
                when(winner.stamp),
                other.zid,
                when(other.stamp),
            )

    def _server_went(self, name: str, server: Server) -> list[Callable[[], None]]:
        servers = self._servers.setdefault(name, {})
        zid = server.zid
        known = servers.get(zid)
        if known is None or known.stamp != server.stamp:
            return []  # unknown, or a predecessor already counted dead
        del servers[zid]
        mine = self._mine.get(name)
        if mine is not None and self._resolution.kept(name, [mine, server]) is not server:
            return []  # one that yielded to this process's own (rule 22): it held nothing here
        if servers:  # one of two that yielded: its consumers reconcile with the kept (rule 20)
            return [functools.partial(self._hearer.reachable, name)]
        stopped = NameAt(name, zid) in self._stopped
        self._gone[name] = "stopped" if stopped else "died"
        self._last[name] = zid
        actions: list[Callable[[], None]] = [functools.partial(self._events.server_gone, name)]
        if stopped:
            return actions
        supervisor = server.supervisor
        if supervisor == "none" or (supervisor != self._zid and supervisor not in self._procs):
            actions.append(functools.partial(self._hearer.lost, name))
        else:
            self._awaiting[name] = supervisor  # lost if its supervisor goes too
        return actions
