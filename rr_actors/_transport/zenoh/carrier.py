"""The Zenoh carrier: one process's membership of a system of registrars over Eclipse Zenoh.

Why publish/subscribe and not Zenoh's queryable + `get`: a registrar's messages are
one-way (`StatusNotice`, `Unload`, ... want no answer; a `Load` is answered when its
load is done, possibly minutes later), and an answer is just another one-way message
back. A `get` would hold a Zenoh query open (and bounded by its own timeout) for as long
as a load runs, and its answers would come on Zenoh's threads. With puts, every message
is a frame of the AF_UNIX carrier (`codec.frame`: token + pickle; the reply stays with
the sender under the token) behind a small header (`wire`), and the failure of a
peer is seen through liveliness tokens, not through a query's end:

```
 process A (sender)                                      process B (serves "erm")
 peer.tell(Load) ─ frame, token → waiting ─► outbox "erm" ── put rr/<s>/reg/erm ──►
                                               (its writer thread)      subscriber callback
                                                                          │ (never blocks:
                                                                          ▼  queues it)
                                                          inbox (A, message): decode thread
                                                          unpickle; stand-in reply; tell erm
 inbox (B, answer): decode thread ◄─ put rr/<s>/ans/<A> ◄── outbox "A" ◄── reply.set_result
   waiting.pop(token).set_result(value)                     (B's writer thread for A)

 liveliness rr/<s>/live/**  ─► presence thread: tokens of processes, registrars, claims,
                                "stopped" marks ─► fail waiting replies, peer_lost,
                                peer_reachable
```

Who does what (each collaborator owns its state; they meet only through method calls):

- `carrier` (here): `ZenohMember`, the Transport surface (resolve, serve, run,
  names, close), one name one server, sending; `ZenohPeer`;
- `outbox`: `Outboxes`, one writer thread per destination key, the heal ping;
- `inbox`: `Inbox`, the decode threads, delivery, version refusal, and the replies
  waiting for answers;
- `presence`: `Presence`, the liveliness tables and the presence thread; it reports
  what follows to the member (`PresenceEvents`: process_gone, server_gone, lost,
  reachable);
- `wire`: key expressions and the frame header.

Never on an actor's thread: a registrar's actor (and any `Actor`: `on_actor_thread`) must
answer its next message, a supervisor's heartbeat included (`hang` tolerance 0.75 s by
default), however slow the network is. So there `resolve` and `route` never ask the
network; what this process's presence heard decides:

- a name served now: sent at once, as from any thread;
- a name heard to stop cleanly: `RegistrarStoppedError` at once (it holds nothing, rule
  12; a registrar served again under its name is a new one, and reconciles itself);
- a name never heard of, or heard to die (a restart may be served already, its token
  still on its way here): its peer comes at once and each message to it is framed and
  queued on the name's outbox (`send_when_served`); the writer thread asks the network,
  then puts it to the server found, or fails its reply (`UnknownRegistrarError`, or
  `RegistrarUnavailableError` for one that died). One queue per name keeps the order
  of what this process sends to it, before and after it is seen served.

Why not trust the tables alone: they may lag the network (a consumer's first call, or
a restarted provider's `ReconcileAsk`, can overtake its token here, and the answer, the
status or the `Reconcile` must still reach it; a process that just joined has not heard
the history yet). Why not wait on the actor: a router slow under load answers in up to
`ASK_TIMEOUT` (1 s), and a manager whose actor does not answer its heartbeat in time is
killed as hung. A user's thread (a call, `run`) still asks the network inline: its
caller waits anyway, and gets `UnknownRegistrarError` at once.

One name, one server: `serve` first declares a claim token, then asks the network for
servers and claims of the name. A server of another process is a `DuplicateNameError`;
of two claims that see each other the lower Zenoh id wins; a claim that sees a higher
one waits until that one either serves (then it yields) or withdraws. A claim is held
until the registrar's token is declared, so a rival never sees it go before the token
comes. (The router orders declarations and queries, so of two claims at least one sees
the other.) A process attached through a router that does not answer serves nothing: it
cannot hear the rest of the system (`Presence.question`).

Through cuts and heals (rule 22): a name whose server went beyond a cut is lost there
(rule 19), and may be served on this side; once the link heals, both registrars' tokens
are seen everywhere. Each carries the clock stamp of when it began to serve: the one
served first is kept, and the process that serves the other makes it yield
(`served_elsewhere`): ERROR, its subscriber and token go, it unloads what it serves and
stops; its consumers, wherever they are, reconcile with the one kept (rule 20).
"""

from __future__ import annotations

import contextlib
import logging
import struct
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import zenoh

from rr_actors._core.actor import on_actor_thread
from rr_actors._core.bus import Subscription
from rr_actors._core.directory import DIRECTORY, Peer
from rr_actors._core.hlc import CLOCK
from rr_actors._transport.base import Address, Endpoint
from rr_actors._transport.messenger import (
    Link,
    Lost,
    Outgoing,
    Remote,
    check_size,
    encode,
    send,
    tell_lost,
    tell_reachable,
)
from rr_actors._transport.zenoh.events import EventExport, EventFeed
from rr_actors._transport.zenoh.inbox import Inbox, Local
from rr_actors._transport.zenoh.outbox import DRAIN_TIMEOUT, Outbox, Outboxes
from rr_actors._transport.zenoh.presence import ASK_TIMEOUT, Presence, Server, rank, when
from rr_actors._transport.zenoh.wire import (
    ANSWER,
    MESSAGE,
    VERSION,
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
    UnknownServerError,
    _known_names,
)

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.seal import Seal

__all__ = ["ZenohMember"]

logger = logging.getLogger("rr_actors")


class ZenohPeer(Remote):
    """A registrar of another process of the system, reached over Zenoh (`tell`, `run`:
    `Remote`; its route is its key and the server seen for it)."""

    def __init__(self, member: ZenohMember, name: str) -> None:
        self.name = name
        self._member = member

    def route(self) -> _Route:
        return self._member.route(self.name)

    def gone(self) -> RrError:
        return self._member._gone_error(self.name)

    def tell(self, message: Any) -> None:
        """Send `message` (`Remote.tell`); on an actor's thread, to a registrar this
        process does not see served, without waiting: `ZenohMember.send_when_served`."""
        member = self._member
        if on_actor_thread() and member.unserved(self.name):
            member.send_when_served(self, message)
        else:
            send(self, message)


class _WhenServed:
    """A message an actor sent to a registrar this process did not see served: on the
    name's writer thread, the network is asked, then it is put (or failed)."""

    __slots__ = ("member", "outbox", "outgoing", "peer")

    def __init__(
        self, member: ZenohMember, peer: ZenohPeer, outgoing: Outgoing, outbox: Outbox
    ) -> None:
        self.member = member
        self.peer = peer
        self.outgoing = outgoing
        self.outbox = outbox

    def __call__(self) -> None:
        self.member._put_when_served(self.peer, self.outgoing, self.outbox)

    def dropped(self) -> None:
        """The outbox closed before it ran: its reply fails (nothing was sent)."""
        self.member._fail_unsent(self.outgoing, self.member._unsent_error(self.peer.name))


class _Route:
    """The way to registrar `name` now: the server seen for it, its outbox (`Route`)."""

    __slots__ = ("_member", "limit", "name", "pending", "zid")

    def __init__(self, member: ZenohMember, name: str, zid: str, limit: int) -> None:
        self._member = member
        self.name = name
        self.zid = zid
        self.limit = limit
        self.pending = member._inbox.replies  # (one table: answers come on one key)

    def send(self, data: bytes) -> bool:
        member = self._member
        outbox = member._outbox(member._keys.registrar(self.name), self.zid)
        return (  # (gone meanwhile: its presence may have missed this reply)
            member._presence.server(self.name) is not None
            and outbox is not None
            and outbox.send(envelope(MESSAGE, member.zid, data, CLOCK.send()))
        )

    def broken(self) -> bool:
        return False  # (the server went: its presence fails what waits on it)


class ZenohMember:
    """This process's membership of a system over an open Zenoh session.

    Args:
        system: the system's name (every key starts with `rr/<system>/`).
        session: the open session (router or client mode).
        address: what other processes of this host join through (the router's address).
        speakers: the Zenoh ids of the processes `supervised_by` can name, by pid (the
            router of this host, for a process that attached through it).
        on_close: called once the member closed (with the member).
        link_trouble: says why a registrar may not be seen (`ZenohNetwork`'s connect
            endpoints it has no link to), as the end of an `UnknownRegistrarError`'s
            message; `""` when nothing is wrong.
        router: the Zenoh id of the router this process attached through (`None`: this
            process is a router); what it hears counts only while that one answers.
        seal: seals the event batches this process sends and opens those it gets
            (`events`); `None` without TLS.
    """

    def __init__(
        self,
        system: str,
        session: zenoh.Session,
        address: Address,
        *,
        speakers: dict[int, str] | None = None,
        on_close: Callable[[ZenohMember], None] | None = None,
        link_trouble: Callable[[], str] | None = None,
        router: str | None = None,
        seal: Seal | None = None,
    ) -> None:
        self.system = system
        self.zid = str(session.zid())
        self._seal = seal
        self.closed = False
        self._session = session
        self._speakers = dict(speakers or {})
        self._supervisor: str | None = None  # set by `supervised_by`: nobody until then
        self._on_close = on_close
        self._address = address
        self._link_trouble = link_trouble
        self._keys = Keys(system)
        self._lock = threading.Lock()
        self._locals: dict[str, Local] = {}
        self._stop_marks: dict[str, Any] = {}
        self._peers: dict[str, ZenohPeer] = {}
        self._outboxes = Outboxes(session, self._keys)
        self._inbox = Inbox(self)
        self._presence = Presence(
            system, session, self.zid, self, on_token=self._inbox.process_token, router=router
        )
        self._answers = session.declare_subscriber(
            self._keys.answers(self.zid), self._inbox.on_answer
        )
        self._pings = session.declare_queryable(
            self._keys.ping(self.zid), lambda query: query.reply(query.key_expr, b"")
        )
        self._proc_token = session.liveliness().declare_token(self._keys.proc(self.zid))
        self._events = EventExport(session, self._keys, self.zid, seal)  # (the system's stream)
        DIRECTORY.add_resolver(self.resolve, self.names)

    @property
    def session(self) -> zenoh.Session:
        """The open Zenoh session (for `ZenohNetwork.services`)."""
        return self._session

    # -- the Transport interface ---------------------------------------------------------

    @property
    def address(self) -> Address:
        """What other processes of this host join through (the router's address)."""
        return self._address

    def resolve(self, name: str) -> Peer | None:
        """A peer for registrar `name` of another process of this system.

        A name not heard of yet is asked of the network (at most `ASK_TIMEOUT` seconds),
        but not on an actor's thread: there its peer comes at once, and each message
        sent to it is held on the name's writer thread until the network answered
        (`send_when_served`).

        Raises:
            UnknownRegistrarError: nobody serves `name` on this system (the message names
                the system).
            RegistrarUnavailableError: the network did not answer in time, and nothing
                heard here says that `name` is served.
        """
        if self.closed or name in self._locals:
            return None  # served here: the directory's own record says stopped or died
        known = self._presence.serves(name)  # (served elsewhere now: before a local record)
        if not known and not isinstance(DIRECTORY.gone_error(name), UnknownRegistrarError):
            return None  # a registrar of this process that stopped or died
        known = known or self._presence.gone(name) is not None
        if not known and NAME.fullmatch(name):
            if on_actor_thread():
                known = True  # (asked by its messages, off this thread)
            else:
                why = self._presence.question(name)
                known = self._presence.serves(name)
                if not known and why is not None:
                    raise RegistrarUnavailableError(
                        f"cannot tell whether registrar {name!r} is served on system "
                        f"{self.system!r}: {why}"
                    )
        if not known:
            raise self._unknown_error(name)
        with self._lock:
            return self._peers.setdefault(name, ZenohPeer(self, name))

    def _unknown_error(self, name: str) -> UnknownRegistrarError:
        return UnknownRegistrarError(  # the known: this process's registrars too
            f"no registrar named {name!r} on system {self.system!r}"
            + _known_names(name, DIRECTORY.names() - {name})
            + (self._link_trouble() if self._link_trouble is not None else "")
        )

    def wait_served(self, name: str, *, timeout: float) -> bool:
        """Whether registrar `name` is served (here or by another process) within `timeout`
        seconds: returns as soon as its token is seen (`Presence.wait_serving`)."""
        if name in self._locals:
            return True
        return self._presence.wait_serving(name, timeout=timeout)

    def names(self) -> list[str]:
        """The registrars of other processes of the system that serve now."""
        if self.closed:
            return []
        return self._presence.names()

    def serve(self, endpoint: Endpoint) -> None:
        """Make a registrar of this process reachable (see the module docstring).

        Raises:
            DuplicateNameError: another process of the system serves that name.
            RegistrarUnavailableError: the network did not say in time whether another
                process serves it (`Presence.wait_turn`): not served, try again.
            RegistrarStoppedError: this process left the system.
        """
        name = endpoint.name
        if self.closed:
            raise RegistrarStoppedError("this process left the system")
        old = self._locals.get(name)
        if old is not None:  # a registrar restarted in this process
            self._unserve(old, stopped=False)
        mark = self._stop_marks.pop(name, None)
        if mark is not None:
            mark.undeclare()
        claim = self._session.liveliness().declare_token(self._keys.claim(NameAt(name, self.zid)))
        try:
            self._presence.wait_turn(name)
            local = Local(endpoint)
            local.stamp = CLOCK.now()  # (after every registration heard of: rule 22)
            supervisor = self._supervisor or (
                self.zid if DIRECTORY.restart_expected(name) else "none"
            )
            local.subscriber = self._session.declare_subscriber(
                self._keys.registrar(name),
                lambda sample: self._inbox.on_message(local, sample),
            )
            token_key = self._keys.server(
                ServerKey(name, self.zid, supervisor, local.max_message_bytes, local.stamp)
            )
            local.token = self._session.liveliness().declare_token(token_key)
        finally:  # after the token: a rival sees this one serve before the claim goes
            claim.undeclare()  # type: ignore[no-untyped-call]
        with self._lock:
            self._locals[name] = local
        rival = self._presence.server(name)  # (one heard between the turn and here)
        if rival is not None:
            self.served_elsewhere(name, rival)
        self._barrier(token_key)
        threading.Thread(
            target=self._watch, args=(local,), name=f"rr-zwatch-{name}", daemon=True
        ).start()
        endpoint.listening()

    def run(self, name: str, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """Run `fn(registrar)` where registrar `name` lives (see `Transport.run`)."""
        local = self._locals.get(name)
        if local is not None:
            return local.endpoint.run(fn)
        try:
            peer = self.resolve(name)
        except UnknownRegistrarError as exc:
            raise UnknownServerError(str(exc)) from None
        if not isinstance(peer, ZenohPeer):
            raise UnknownServerError(f"no registrar named {name!r} on system {self.system!r}")
        return peer.run(fn, timeout=timeout)

    def supervised_by(self, pid: int | None) -> None:
        """Say that process `pid` speaks for the registrars served here from now on (see
        `Transport.supervised_by`): published as `<sup>` in their tokens. Only the router
        this process attached through is known by its pid; any other `pid` (the owner of
        a `RemoteRegistrar` that is not the router), and `None`, publish `none`: such a
        registrar is lost when its process dies (its owner's death watch says so too)."""
        self._supervisor = None if pid is None else self._speakers.get(pid)

    def serving_trouble(self, name: str) -> tuple[float, str] | None:
        """Always `None`: a Zenoh subscriber has no accept queue to run out of."""
        return None

    def subscribe_events(
        self, callback: Callable[[Any], object], *, window: float, maxsize: int
    ) -> Subscription[Any]:
        """Every event of every process of the system (see `ZenohNetwork.subscribe_events`).

        Raises:
            RegistrarStoppedError: this process left the system.
        """
        if self.closed:
            raise RegistrarStoppedError("this process left the system")
        feed = EventFeed(self._session, self._keys, window, self._seal)
        subscription = feed.subscribe(callback, maxsize)
        self._events.wait_sending(ASK_TIMEOUT)  # (this process's own, from now on)
        return subscription

    def close(self) -> None:
        """Leave the system: stop serving, fail what waits, put what was sent (for
        `DRAIN_TIMEOUT` seconds at most), close the session."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            locals_ = list(self._locals.values())
        DIRECTORY.remove_resolver(self.resolve)
        for local in locals_:
            self._unserve(local, stopped=local.endpoint.stopped_cleanly())
        self._inbox.replies.fail(None, RegistrarStoppedError("this process left the system"))
        self._events.close()
        self._outboxes.close(drain=DRAIN_TIMEOUT)  # (what was sent before goes out first)
        self._inbox.close()
        self._presence.close()
        with contextlib.suppress(Exception):
            self._session.close()  # type: ignore[no-untyped-call]
        if self._on_close is not None:
            self._on_close(self)

    # -- serving ---------------------------------------------------------------------------

    def _barrier(self, key: str) -> None:
        """Return once the router this process talks to has seen the token `key`.

        A query after a declaration reaches the router after it (one link, in order), so
        its answer means other processes resolving the name find it.
        """
        with contextlib.suppress(Exception):
            for _reply in self._session.liveliness().get(key, timeout=ASK_TIMEOUT):
                pass

    def _watch(self, local: Local) -> None:
        local.endpoint.wait_ended()
        self._unserve(local, stopped=local.endpoint.stopped_cleanly())
        if local.yielded:  # its name is the kept one's now: this process's consumers of
            # it reconcile with that one (rule 20), as other processes' do (presence)
            self.reachable(local.name)

    def served_elsewhere(self, name: str, server: Server) -> None:
        """Another process serves registrar `name` (the presence thread): if this process
        serves it too and rule 22 keeps the other one (registered first, by its clock
        stamp; of equal stamps, the lower Zenoh id), this one yields.

        Yielding, as Erlang's `global` resolves a name registered on both sides of a
        netsplit: an ERROR line, its subscriber and token go (nothing more reaches it;
        its consumers elsewhere see it go and reconcile with the one kept), and the
        registrar unloads what it serves and stops (`Endpoint.yield_name`). The process
        of the one kept does nothing: this one sees it too, and yields.
        """
        local = self._locals.get(name)
        if local is None or server.rank > rank(local.stamp, self.zid):
            return
        reason = (
            f"registrar {name!r} of system {self.system!r} is served by process "
            f"{server.zid} too, since {when(server.stamp)}, before this one "
            f"(process {self.zid}, since {when(local.stamp)}): one name is one registrar "
            f"(rule 22), and the one served first is kept"
        )
        with local.lock:
            if local.ended:
                return
            local.ended = local.yielded = True
            with contextlib.suppress(Exception):  # (first: nothing more reaches it)
                local.subscriber.undeclare()
            with contextlib.suppress(Exception):
                local.token.undeclare()
        with self._lock:
            if self._locals.get(name) is local:
                del self._locals[name]
        logger.error(
            "%s; this one stops serving: it unloads what it serves and stops, and its "
            "consumers reconcile with the other one (an id it does not hold is FATAL)",
            reason,
        )
        local.endpoint.yield_name(reason)

    def _unserve(self, local: Local, *, stopped: bool) -> None:
        """Stop serving `local`; a clean stop is marked before the token goes."""
        with local.lock:
            if local.ended:
                return
            local.ended = True
            if stopped:  # the mark goes out before the token: peers say "stopped"
                with contextlib.suppress(Exception):
                    self._stop_marks[local.name] = self._session.liveliness().declare_token(
                        self._keys.stopped(NameAt(local.name, self.zid))
                    )
            with contextlib.suppress(Exception):
                local.token.undeclare()
            with contextlib.suppress(Exception):
                local.subscriber.undeclare()
        with self._lock:
            if self._locals.get(local.name) is local:
                del self._locals[local.name]

    # -- sending ---------------------------------------------------------------------------

    def _gone_error(self, name: str) -> RrError:
        if self.closed:
            return RegistrarStoppedError("this process left the system")
        if self._presence.gone(name) == "stopped":
            return RegistrarStoppedError(f"registrar {name!r} was stopped")
        return RegistrarUnavailableError(
            f"registrar {name!r} of system {self.system!r} cannot be reached (its process "
            f"died, or a link on the way to it is down: this host's own, or one beyond the "
            f"router it is reached through)"
        )

    def route(self, name: str) -> _Route:
        """The way to registrar `name` of another process now (`ZenohPeer.route`).

        Raises:
            RegistrarUnavailableError: no process serves it now (asked of the network,
                but not on an actor's thread: there, what presence heard decides).
            RegistrarStoppedError: it was stopped, or this process left the system.
        """
        server = self._presence.server(name)
        if server is None and not self.closed and not on_actor_thread():
            self._presence.ask(name)  # maybe served again, not yet heard here
            server = self._presence.server(name)
        if server is None:
            raise self._gone_error(name)
        return _Route(self, name, server.zid, server.limit)

    def unserved(self, name: str) -> bool:
        """Whether this process sees no server of registrar `name` and did not hear it
        stop (never heard of, or died: maybe served again, not yet heard here)."""
        presence = self._presence
        return (
            not self.closed and presence.server(name) is None and presence.gone(name) != "stopped"
        )

    def send_when_served(self, peer: ZenohPeer, message: Any) -> None:
        """Send `message` to registrar `peer.name`, which this process does not see
        served (`unserved`), without waiting (an actor's thread; see the module
        docstring).

        It is framed here and queued on the name's outbox, in order with what is sent
        to that name after it; there the network is asked (`Presence.ask`), then the
        frame is put to the server found, or its reply fails: `UnknownRegistrarError` if
        nobody serves the name (`RegistrarUnavailableError` if it was heard to die),
        `MessageTooLargeError` if it is over that server's
        `max_message_bytes`. A message without a reply is then dropped (logged at debug
        level), as the registrar drops one that cannot be sent at once.

        Raises:
            ConfigError: the message cannot be pickled.
            RegistrarStoppedError: this process left the system.
        """
        outgoing = encode(peer.name, message)
        for _attempt in (1, 2):  # (the second: its outbox was just retired, nobody's)
            # (its publisher is declared after the network was asked: a liveliness query
            # right after a publisher's declaration can come back empty at once)
            outbox = self._outbox(self._keys.registrar(peer.name), declared=False)
            if outbox is None:
                break
            if outbox.run(_WhenServed(self, peer, outgoing, outbox)):
                return
        raise self._gone_error(peer.name)

    def _put_when_served(self, peer: ZenohPeer, outgoing: Outgoing, outbox: Outbox) -> None:
        """`send_when_served`'s second half, on `outbox`'s writer thread (the name's)."""
        name, presence = peer.name, self._presence
        server = presence.server(name)
        if server is None and not self.closed and presence.gone(name) != "stopped":
            presence.ask(name)
            server = presence.server(name)
        if server is None:  # nobody's: what waits behind it fails too, and its writer ends
            self._fail_unsent(outgoing, self._unsent_error(name))
            self._outboxes.retire(outbox)
            return
        outbox.declare()
        if outbox.pinged != server.zid:  # just seen: a put before its ping may be lost
            self._outboxes.until_answered(server.zid)
            outbox.pinged = server.zid
        try:
            check_size(outgoing, name, server.limit)
        except RrError as exc:
            self._fail_unsent(outgoing, exc)
            return
        replies = self._inbox.replies
        if outgoing.reply is not None:
            replies.expect(outgoing, peer, server.limit)

        def lost() -> None:  # (gone meanwhile: its presence may have missed this reply)
            if outgoing.reply is None or replies.forget(outgoing.token):
                self._fail_unsent(outgoing, self._gone_error(name))

        if outbox.closed or presence.server(name) is None:
            lost()
            return
        outbox.put(envelope(MESSAGE, self.zid, outgoing.data, CLOCK.send()), lost)

    def _unsent_error(self, name: str) -> RrError:
        """The error of a message to `name` that found no server: gone, or unknown."""
        if self.closed or self._presence.gone(name) is not None:
            return self._gone_error(name)
        return self._unknown_error(name)

    @staticmethod
    def _fail_unsent(outgoing: Outgoing, error: RrError) -> None:
        if outgoing.reply is not None:
            outgoing.reply.set_error(error)
        else:
            logger.debug("%s not sent: %s", type(outgoing.message).__name__, error)

    def _outbox(self, key: str, zid: str | None = None, *, declared: bool = True) -> Outbox | None:
        """The outbox of `key`, whose subscriber is in process `zid` (if known: then the
        first put of a new outbox waits for that process's answer to a ping); see
        `Outboxes.get` for `declared`."""
        if self.closed:
            return None
        return self._outboxes.get(key, zid, declared=declared)

    def answer_to(self, sender: str, data: bytes, on_lost: Lost | None) -> bool:
        """Send an answer frame to process `sender`; False if it is gone (not sent).

        (A sender whose token has not been seen yet is not gone: its message may overtake
        its token on the way through this process's threads.)
        """
        if self._presence.unreachable(sender):
            return False
        outbox = self._outbox(self._keys.answers(sender), sender)
        return outbox is not None and outbox.send(
            envelope(ANSWER, self.zid, data, CLOCK.send()), on_lost
        )

    def member(self, zid: str) -> bool:
        """Whether process `zid`'s liveliness token is here now (see `Presence.member`)."""
        return self._presence.member(zid)

    def refuse_version(self, sender: str, token: int) -> None:
        """Tell process `sender` that its message `token` was of another version."""
        outbox = self._outbox(self._keys.answers(sender))
        if outbox is not None:
            outbox.send(header(VERSION, self.zid) + struct.pack("!i", 8) + struct.pack("<Q", token))

    # -- what presence reports (the presence thread, in order) -----------------------------

    def process_gone(self, zid: str) -> None:
        """Process `zid`'s token went: its answer outbox closes, its inboxes finish."""
        answers = self._outboxes.pop(self._keys.answers(zid))
        if answers is not None:
            answers.close()
        self._inbox.finish(zid)  # what it sent before it went is still delivered

    def server_gone(self, name: str) -> None:
        """The last server of `name` went: what waits on it fails, its outbox closes."""
        self._inbox.replies.fail(name, lambda: self._gone_error(name))
        outbox = self._outboxes.pop(self._keys.registrar(name))
        if outbox is not None:
            outbox.close()

    def lost(self, name: str) -> None:
        """Registrar `name` is gone for good: every endpoint served here hears it."""
        tell_lost([local.endpoint for local in list(self._locals.values())], name, self.system)

    def reachable(self, name: str) -> None:
        """Registrar `name` is back from the same process (a healed link)."""
        tell_reachable([local.endpoint for local in list(self._locals.values())], name, self.system)


if TYPE_CHECKING:  # mypy checks that the member is the messenger's link
    _link: type[Link] = ZenohMember
