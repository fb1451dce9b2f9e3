"""The Zenoh carrier: one process's link to a system of registrars over Eclipse Zenoh.

Puts both ways, presence by liveliness tokens. How a message crosses, and why:
docs/explanation/inside.md ("The Zenoh carrier").
"""

from __future__ import annotations

import contextlib
import functools
import logging
import struct
import sys
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import zenoh

from rr_actors._core.actor import on_actor_thread
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.hlc import CLOCK
from rr_actors._transport.messenger import (
    Carrier,
    Endpoint,
    Listening,
    Lost,
    Messenger,
    Route,
    too_large,
)
from rr_actors._transport.resolve import Sided
from rr_actors._transport.zenoh import callbacks
from rr_actors._transport.zenoh.callbacks import tracked
from rr_actors._transport.zenoh.link import DRAIN_TIMEOUT, Inbox, Outbox, Outboxes
from rr_actors._transport.zenoh.presence import ASK_TIMEOUT, Presence, Server
from rr_actors._transport.zenoh.wire import (
    ANSWER,
    MESSAGE,
    VERSION,
    HostKey,
    Keys,
    NameAt,
    ServerKey,
    envelope,
    header,
)
from rr_actors.config import NAME
from rr_actors.errors import (
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    UnknownRegistrarError,
    _known_names,
)

logger = logging.getLogger("rr_actors")


class _Route(Route):
    """The server seen for `name` (its process `zid`); replies wait in the one table. To
    a server given (`told`, `route(name, server)`): sent to whether it is seen or not."""

    __slots__ = ("name", "told", "zid")

    def __init__(self, carrier: ZenohCarrier, name: str, zid: str, limit: int | None) -> None:
        super().__init__(sys.maxsize if limit is None else limit, carrier.replies)
        self.name, self.zid, self.told = name, zid, limit is None


class _Held(Route):
    """A message to `name`, not seen served, held on the name's lane (its outbox) until
    the network says who serves it: its reply waits here until then (`_WhenServed`)."""

    __slots__ = ("name",)

    def __init__(self, name: str) -> None:
        super().__init__(sys.maxsize)  # (checked once its server is known)
        self.name = name


class _WhenServed:
    """The lane's task of a `_Held` message: found, checked, its reply moved, put."""

    __slots__ = ("carrier", "data", "held", "lane")

    def __init__(self, carrier: ZenohCarrier, held: _Held, data: bytes, lane: Outbox) -> None:
        self.carrier = carrier
        self.held = held
        self.data = data
        self.lane = lane

    def __call__(self) -> None:  # (on the lane's thread)
        carrier, held, name = self.carrier, self.held, self.held.name
        route = carrier.found(name, self.lane)
        if isinstance(route, RrError):  # this one fails first, then what waits behind it:
            self.unsent(route)  # refused in the order told, never a later one first
            carrier.retire(self.lane, route)
            return
        waiting = list(held.pending.items())  # (its reply, if any)
        error = too_large(waiting[0][1][1] if waiting else None, self.data, name, route.limit)
        if error is not None:
            self.unsent(error)
            return
        held.pending.clear()
        for token, (reply, message, peer, _limit) in waiting:
            route.pending[token] = (reply, message, peer, route.limit)
        if not carrier.put_now(self.lane, name, self.data) and (
            not waiting or route.pending.forget(waiting[0][0])
        ):  # (gone meanwhile: what ended it may have missed this reply)
            held.pending.update(waiting)
            self.unsent(carrier.gone_error(name))

    def unsent(self, error: RrError) -> None:
        if self.held.pending:
            self.held.pending.fail(None, error)
        else:
            logger.debug("a message to %s was not sent: %s", self.held.name, error)

    def dropped(self) -> None:
        """The lane closed before it ran: its reply fails, as the one before it did."""
        self.unsent(self.lane.refusal or self.carrier.unreached(self.held.name))


class Local(Listening):
    """A registrar served here: its subscriber and token, when it began to serve (rule 22)."""

    def __init__(self, carrier: ZenohCarrier, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self.carrier = carrier
        self.max_message_bytes = endpoint.max_message_bytes
        self.subscriber: Any = None
        self.token: Any = None
        self.token_key = ""
        self.stamp = 0
        self.side = 0  # the hosts this process heard as it began to serve (`Sided`)
        self.members = 0  # the system's members then, as it counted them (0: unknown)

    @property
    def who(self) -> str:
        return self.carrier.zid

    @property
    def rank(self) -> tuple[int, int]:
        return (self.stamp, int(self.carrier.zid, 16))


def _pong(query: zenoh.Query) -> None:
    query.reply(query.key_expr, b"")


class ZenohCarrier:
    """This process's `Carrier` over an open Zenoh session: docs/explanation/inside.md
    ("The Zenoh carrier's threads, names and heals")."""

    def __init__(
        self,
        messenger: Messenger,
        session: zenoh.Session,
        *,
        speakers: dict[int, str] | None = None,
        on_close: Callable[[], None] | None = None,
        link_trouble: Callable[[], str] | None = None,
        router: str | None = None,
        on_leave: Callable[[], None] | None = None,
        members: int = 0,
    ) -> None:
        self.messenger = messenger
        self._router = router
        self._system_members = members
        self._host_lock = threading.Lock()
        self._host_token: Any = None
        self._host_most = 0
        self.system = messenger.system
        self.session = session
        self.zid = str(session.zid())
        self._on_leave = on_leave
        self.keys = Keys(self.system)
        self._speakers = dict(speakers or {})
        self._on_close = on_close
        self._link_trouble = link_trouble
        self._stop_marks: dict[str, Any] = {}
        self._leaving: dict[int, Callable[[], object]] = {}  # `on_leave`'s, by number
        self._leaving_numbers = 0
        self._left = False  # (under `_host_lock`, as `_leaving`)
        self._outboxes = Outboxes(session, self.keys)
        self._inbox = Inbox(self)
        self.replies = self._inbox.replies
        self.presence = Presence(
            self.system,
            session,
            self.zid,
            self,
            on_token=self._inbox.process_token,
            router=router,
            hearer=messenger,
            resolution=messenger.resolution,
            on_hosts=self._hosts_heard if router is None else None,
        )
        self._answers = session.declare_subscriber(
            self.keys.answers(self.zid), tracked(session, self._inbox.on_answer)
        )
        self._pings = session.declare_queryable(self.keys.ping(self.zid), tracked(session, _pong))
        self._proc_token = session.liveliness().declare_token(self.keys.proc(self.zid))
        if router is None:  # (a host's router: its host token, rule 22's sides)
            self._hosts_heard(1)

    @property
    def closed(self) -> bool:
        return self.messenger.closed

    # -- the Carrier -------------------------------------------------------------------

    def knows(self, name: str) -> bool:
        """`Carrier.knows`; a name not heard of is asked of the network (not on an actor)."""
        presence = self.presence
        known = presence.serves(name)  # (served elsewhere now: before a local record)
        if not known and not isinstance(DIRECTORY.gone_error(name), UnknownRegistrarError):
            return False  # a registrar of this process that stopped or died
        known = known or presence.gone(name) is not None
        if not known and NAME.fullmatch(name):
            if on_actor_thread():
                known = True  # (asked by its messages, off this thread)
            else:
                why = presence.question_until_seen(name)  # (an empty answer, asked again)
                known = presence.serves(name)
                if not known and why is not None:
                    raise self._untold(name, why)
        if not known:
            raise self._unknown_error(name)
        return True

    def serve(self, endpoint: Endpoint) -> Local:
        """Claim the name, then declare subscriber and token; a rival heard meanwhile is
        told to the messenger (rule 22); return once the router saw the token. Raises as
        `wait_turn`."""
        name, keys, session = endpoint.name, self.keys, self.session
        mark = self._stop_marks.pop(name, None)
        if mark is not None:
            mark.undeclare()
        claim = session.liveliness().declare_token(keys.claim(NameAt(name, self.zid)))
        local: Local | None = None
        try:
            self.presence.wait_turn(name)
            local = Local(self, endpoint)
            local.stamp = CLOCK.now()  # (after every registration heard of: rule 22)
            local.side, local.members = self.presence.hosts(), self._members()
            local.subscriber = session.declare_subscriber(
                keys.registrar(name),
                tracked(session, functools.partial(self._inbox.on_message, local)),
            )
            local.token_key = keys.server(
                ServerKey(
                    name,
                    self.zid,
                    self._speaker(name),
                    local.max_message_bytes,
                    local.stamp,
                    local.side,
                    local.members,
                )
            )
            local.token = session.liveliness().declare_token(local.token_key)
        except BaseException:  # (its subscriber undeclared and let go here, not freed
            if local is not None and local.subscriber is not None:  # on some other thread)
                subscriber, local.subscriber = local.subscriber, None
                with contextlib.suppress(Exception):  # (the first error is the one to tell)
                    subscriber.undeclare()
            raise
        finally:  # after the token: a rival sees this one serve before the claim goes
            claim.undeclare()  # type: ignore[no-untyped-call]
        rival = self.presence.server(name)
        if rival is not None:
            self.served_elsewhere(name, rival)
        self.barrier(local.token_key)
        return local

    def unserve(self, listening: Listening, *, stopped: bool) -> None:
        """Undeclare its subscriber and token on this thread (`callbacks`)."""
        assert isinstance(listening, Local)
        subscriber, token = listening.subscriber, listening.token
        listening.subscriber = listening.token = None
        first, then = (subscriber, token) if listening.yielded else (token, subscriber)
        if stopped and not listening.yielded:
            self.mark_stopped(listening.name)
        for declared in (first, then):
            with contextlib.suppress(Exception):
                declared.undeclare()

    def _members(self) -> int:
        """The system's members as counted here (rule 22's `majority`; 0: unknown)."""
        return self._system_members or self.presence.most(self._router)

    def _hosts_heard(self, count: int) -> None:
        """`count` hosts were heard at once: the host token says so if that is the most."""
        with self._host_lock:
            if count <= self._host_most or self.closed:
                return
            old, self._host_most = self._host_token, count
            self._host_token = self.session.liveliness().declare_token(
                self.keys.host(HostKey(self.zid, count))
            )
        if old is not None:
            with contextlib.suppress(Exception):
                old.undeclare()

    def answer(self, process: str, data: bytes, on_lost: Lost | None) -> bool:
        """`Carrier.answer` to a Zenoh id (one whose token is not seen yet is not gone)."""
        if self.presence.unreachable(process):
            return False
        outbox = self.outbox(self.keys.answers(process), process)
        return outbox is not None and outbox.send(
            envelope(ANSWER, self.zid, data, CLOCK.send()), on_lost
        )

    def names(self) -> list[str]:
        return self.presence.names()

    def on_leave(self, close: Callable[[], object]) -> Callable[[], None]:
        """Have `close()` called first as this process leaves; returns what forgets it."""
        with self._host_lock:
            if not self._left:
                number = self._leaving_numbers = self._leaving_numbers + 1
                self._leaving[number] = close

                def forget() -> None:
                    with self._host_lock:
                        self._leaving.pop(number, None)

                return forget
        close()
        return lambda: None

    def leave(self) -> None:
        """Close what `on_leave` got, fail what waits, drain, close the session, join."""
        with self._host_lock:
            self._left = True
            leaving, self._leaving = list(self._leaving.values()), {}
        for close in reversed(leaving):  # (newest first)
            try:
                close()
            except Exception:
                logger.exception("system %s: closing what used its session failed", self.system)
        self.replies.fail(None, RegistrarStoppedError("this process left the system"))
        if self._on_leave is not None:
            self._on_leave()
        self._outboxes.close(drain=DRAIN_TIMEOUT)  # (what was sent before goes out first)
        self._inbox.close()
        self.presence.close()
        with contextlib.suppress(Exception):
            self.session.close()  # type: ignore[no-untyped-call]
        if self._on_close is not None:
            self._on_close()
        left = callbacks.wait_ended(self.session)
        if left:
            logger.warning(
                "system %s: %s had not ended %g s after the session closed (one that runs "
                "Python as the interpreter ends aborts the process on CPython < 3.14)",
                self.system,
                ", ".join(left),
                callbacks.END_TIMEOUT,
            )

    def wait_served(self, name: str, *, timeout: float) -> bool:
        """Whether registrar `name` is served (anywhere) within `timeout` seconds."""
        if self.messenger.serving(name) is not None:
            return True
        return self.presence.wait_serving(name, timeout=timeout)

    # -- serving -------------------------------------------------------------------------

    def _speaker(self, name: str) -> str:
        """Who restarts `name` (rule 19): `supervised_by`'s, else this one, else `none`."""
        supervisor = self.messenger.supervisor
        known = None if supervisor is None else self._speakers.get(supervisor)
        return known or (self.zid if DIRECTORY.restart_expected(name) else "none")

    def barrier(self, key: str) -> None:
        """Return once the router has seen the token `key` (a query follows a declaration)."""
        with contextlib.suppress(Exception), callbacks.calling(self.session):
            for _reply in self.session.liveliness().get(key, timeout=ASK_TIMEOUT):
                pass

    def mark_stopped(self, name: str) -> None:
        """Declare `name`'s "stopped" mark (until the name is served here again)."""
        with contextlib.suppress(Exception), callbacks.calling(self.session):
            self._stop_marks[name] = self.session.liveliness().declare_token(
                self.keys.stopped(NameAt(name, self.zid))
            )

    def served_elsewhere(self, name: str, server: Server) -> None:
        self.messenger.served_elsewhere(name, server)

    # -- sending -------------------------------------------------------------------------

    def gone_error(self, name: str) -> RrError:
        if self.closed:
            return RegistrarStoppedError("this process left the system")
        if self.presence.gone(name) == "stopped":
            return RegistrarStoppedError(f"registrar {name!r} was stopped", name)
        return RegistrarUnavailableError(
            f"registrar {name!r} of system {self.system!r} cannot be reached (its process "
            f"died, or a link on the way to it is down: this host's own, or one beyond the "
            f"router it is reached through)"
        )

    def _unknown_error(self, name: str) -> UnknownRegistrarError:
        return UnknownRegistrarError(  # the known: this process's registrars too
            f"no registrar named {name!r} on system {self.system!r}"
            + _known_names(name, DIRECTORY.names() - {name})
            + (self._link_trouble() if self._link_trouble is not None else "")
        )

    def _untold(self, name: str, why: str) -> RegistrarUnavailableError:
        return RegistrarUnavailableError(
            f"cannot tell whether registrar {name!r} is served on system {self.system!r}: {why}"
        )

    def unreached(self, name: str) -> RrError:
        if self.closed or self.presence.gone(name) is not None:
            return self.gone_error(name)
        return self._unknown_error(name)

    def route(self, name: str, server: Sided | None = None) -> Route:
        """The server seen for `name`, else the network is asked; on an actor's thread, to
        a name not seen served: a `_Held` route, sent when served (`send`). To `server`
        (rule 22's other one, `Messenger._claim`): its process's, seen or not."""
        if server is not None:
            return _Route(self, name, server.who, None)
        if on_actor_thread() and self.unseen(name):
            return _Held(name)
        seen = self.presence.server(name)
        if seen is None and not self.closed and not on_actor_thread():
            self.presence.question_until_seen(name)  # maybe served again, not heard yet
            seen = self.presence.server(name)
        if seen is None:
            raise self.gone_error(name)
        return _Route(self, name, seen.zid, seen.limit)

    def send(self, route: Route, data: bytes) -> None:
        """Put `data` on the route's key, in order; a `_Held` one on its name's lane."""
        if isinstance(route, _Held):
            for _attempt in (1, 2):  # (the second: its lane was just retired, nobody's)
                lane = self.outbox(self.keys.registrar(route.name), declared=False)
                if lane is None:
                    break
                if lane.run(_WhenServed(self, route, data, lane)):
                    return
            raise self.gone_error(route.name)
        assert isinstance(route, _Route)
        outbox = self.outbox(self.keys.registrar(route.name), route.zid)
        if (  # (gone meanwhile: its presence may have missed this reply)
            (not route.told and self.presence.server(route.name) is None)
            or outbox is None
            or not outbox.send(envelope(MESSAGE, self.zid, data, CLOCK.send()))
        ):
            raise self.gone_error(route.name)

    def put_now(self, outbox: Outbox, name: str, data: bytes) -> bool:
        """On `outbox`'s thread: put `data` now, in order with what waits behind it."""
        if outbox.closed or self.presence.server(name) is None:
            return False
        return outbox.put(envelope(MESSAGE, self.zid, data, CLOCK.send()))

    # -- sending when served ----------------------------------------------------------------

    def unseen(self, name: str) -> bool:
        presence = self.presence
        return (
            not self.closed and presence.server(name) is None and presence.gone(name) != "stopped"
        )

    def found(self, name: str, outbox: Outbox) -> _Route | RrError:
        """On `outbox`'s thread: the route to `name`'s server (the network asked, bounded),
        or the error; a server just seen gets a ping first (a put before may be lost)."""
        presence = self.presence
        server = presence.server(name)
        why = None
        if server is None and not self.closed and presence.gone(name) != "stopped":
            why = presence.question_until_seen(name)  # (an empty answer, asked again)
            server = presence.server(name)
        if server is None:
            if why is None or self.closed or presence.gone(name) is not None:
                return self.unreached(name)
            return self._untold(name, why)
        outbox.declare()
        if outbox.pinged != server.zid:  # just seen: a put before its ping may be lost
            self._outboxes.until_answered(server.zid)
            outbox.pinged = server.zid
        return _Route(self, name, server.zid, server.limit)

    def retire(self, outbox: Outbox, error: RrError) -> None:
        """On `outbox`'s thread: nobody's from now on; what waits fails with `error`."""
        outbox.refusal = error
        self._outboxes.retire(outbox)

    def outbox(self, key: str, zid: str | None = None, *, declared: bool = True) -> Outbox | None:
        """`Outboxes.get`; `None` once this process left the system."""
        if self.closed:
            return None
        return self._outboxes.get(key, zid, declared=declared)

    # -- what the inbox asks ---------------------------------------------------------------

    def member(self, zid: str) -> bool:
        return self.presence.member(zid)

    def refuse_version(self, sender: str, token: int) -> None:
        outbox = self.outbox(self.keys.answers(sender))
        if outbox is not None:
            outbox.send(header(VERSION, self.zid) + struct.pack("!i", 8) + struct.pack("<Q", token))

    # -- what presence reports (the presence thread, in order) -----------------------------

    def process_gone(self, zid: str) -> None:
        answers = self._outboxes.pop(self.keys.answers(zid))
        if answers is not None:
            answers.close()
        self._inbox.finish(zid)  # what it sent before it went is still delivered

    def server_gone(self, name: str) -> None:
        self.replies.fail(name, lambda: self.gone_error(name))
        outbox = self._outboxes.pop(self.keys.registrar(name))
        if outbox is not None:
            outbox.close()


if TYPE_CHECKING:  # mypy checks that the carrier is the messenger's
    _carrier: type[Carrier] = ZenohCarrier
