"""The Zenoh carrier: one process's link to a system of registrars over Eclipse Zenoh.

Puts both ways, presence by liveliness tokens. How a message crosses, and why:
docs/explanation/inside.md ("The Zenoh carrier").
"""

from __future__ import annotations

import contextlib
import functools
import logging
import struct
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import zenoh

from rr_actors._core.actor import on_actor_thread
from rr_actors._core.directory import DIRECTORY
from rr_actors._core.hlc import CLOCK
from rr_actors._transport.codec import NO_REPLY, Claim, frame
from rr_actors._transport.messenger import (
    Carrier,
    Endpoint,
    Lane,
    Lanes,
    Listening,
    Lost,
    Messenger,
    Remote,
    send,
    send_when_served,
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


class ZenohPeer(Remote):
    """A registrar of another process over Zenoh; its lane is the key's outbox."""

    def __init__(self, carrier: ZenohCarrier, name: str) -> None:
        self.name = name
        self._carrier = carrier

    def tell(self, message: Any) -> None:
        """`Remote.tell`; on an actor's thread, to one not seen served: `send_when_served`."""
        carrier = self._carrier
        if on_actor_thread() and carrier.unseen(self.name):
            send_when_served(self, carrier, message)
        else:
            send(self, message)

    def route(self) -> _Route:
        return self._carrier.route(self.name)

    def gone(self) -> RrError:
        return self._carrier.gone_error(self.name)


class _Route:
    """The server seen for `name` and its outbox (`now`: put at once, on its thread)."""

    __slots__ = ("_carrier", "_now", "limit", "name", "pending", "zid")

    def __init__(
        self, carrier: ZenohCarrier, name: str, server: Server, now: Outbox | None = None
    ) -> None:
        self._carrier = carrier
        self._now = now
        self.name = name
        self.zid = server.zid
        self.limit = server.limit
        self.pending = carrier.replies  # (one table: answers come on one key)

    def send(self, data: bytes) -> bool:
        carrier = self._carrier
        outbox = self._now
        if outbox is not None:  # (on its thread: in order with what waits behind it)
            if outbox.closed or carrier.presence.server(self.name) is None:
                return False
            return outbox.put(envelope(MESSAGE, carrier.zid, data, CLOCK.send()))
        outbox = carrier.outbox(carrier.keys.registrar(self.name), self.zid)
        return (  # (gone meanwhile: its presence may have missed this reply)
            carrier.presence.server(self.name) is not None
            and outbox is not None
            and outbox.send(envelope(MESSAGE, carrier.zid, data, CLOCK.send()))
        )

    def broken(self) -> bool:
        return False  # (the server went: its presence fails what waits on it)


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

    def settle(self) -> None:
        """Settle a rival heard meanwhile (rule 22); return once the router saw its token."""
        carrier = self.carrier
        rival = carrier.presence.server(self.name)
        if rival is not None:
            carrier.served_elsewhere(self.name, rival)
        carrier.barrier(self.token_key)

    def stop(self, *, stopped: bool) -> None:
        """Undeclare its subscriber and token on this thread (`callbacks`)."""
        subscriber, token, self.subscriber, self.token = self.subscriber, self.token, None, None
        first, then = (subscriber, token) if self.yielded else (token, subscriber)
        if stopped and not self.yielded:
            self.carrier.mark_stopped(self.name)
        for declared in (first, then):
            with contextlib.suppress(Exception):
                declared.undeclare()


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

    def peer(self, name: str) -> ZenohPeer | None:
        """`Carrier.peer`; a name not heard of is asked of the network (not on an actor)."""
        presence = self.presence
        known = presence.serves(name)  # (served elsewhere now: before a local record)
        if not known and not isinstance(DIRECTORY.gone_error(name), UnknownRegistrarError):
            return None  # a registrar of this process that stopped or died
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
        return ZenohPeer(self, name)

    def listen(self, endpoint: Endpoint) -> Local:
        """Claim the name, then declare subscriber and token. Raises as `wait_turn`."""
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
        return local

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

    def answer_to(self, process: str, data: bytes, on_lost: Lost | None) -> bool:
        """`Carrier.answer_to` a Zenoh id (one whose token is not seen yet is not gone)."""
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

    def tell_server(self, name: str, server: Sided, claim: Claim) -> None:
        """Rule 22: put `claim` on `name`'s key for its other server (`Messenger._claim`)."""
        outbox = self.outbox(self.keys.registrar(name), server.who)
        if outbox is not None:
            outbox.send(envelope(MESSAGE, self.zid, frame(NO_REPLY, claim), CLOCK.send()))

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

    def route(self, name: str) -> _Route:
        """`ZenohPeer.route` (the network is asked, but not on an actor's thread)."""
        server = self.presence.server(name)
        if server is None and not self.closed and not on_actor_thread():
            self.presence.question_until_seen(name)  # maybe served again, not heard yet
            server = self.presence.server(name)
        if server is None:
            raise self.gone_error(name)
        return _Route(self, name, server)

    # -- sending when served (the messenger's `Lanes`) ---------------------------------------

    def unseen(self, name: str) -> bool:
        presence = self.presence
        return (
            not self.closed and presence.server(name) is None and presence.gone(name) != "stopped"
        )

    def lane(self, name: str) -> Outbox | None:
        """`name`'s outbox, declared on its thread after the network was asked."""
        return self.outbox(self.keys.registrar(name), declared=False)

    def found(self, name: str, lane: Lane) -> _Route | RrError:
        """`Lanes.found`; a server just seen gets a ping first (a put before may be lost)."""
        presence = self.presence
        server = presence.server(name)
        why = None
        if server is None and not self.closed and presence.gone(name) != "stopped":
            why = presence.question_until_seen(name)  # (an empty answer, asked again)
            server = presence.server(name)
        assert isinstance(lane, Outbox)
        outbox = lane
        if server is None:
            if why is None or self.closed or presence.gone(name) is not None:
                return self.unreached(name)
            return self._untold(name, why)
        outbox.declare()
        if outbox.pinged != server.zid:  # just seen: a put before its ping may be lost
            self._outboxes.until_answered(server.zid)
            outbox.pinged = server.zid
        return _Route(self, name, server, now=outbox)

    def retire(self, lane: Lane, error: RrError) -> None:
        assert isinstance(lane, Outbox)
        lane.refusal = error
        self._outboxes.retire(lane)

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
    _lanes: type[Lanes] = ZenohCarrier
