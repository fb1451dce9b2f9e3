"""The Zenoh carrier: one process's membership of a system of registrars over Eclipse Zenoh.

Why publish/subscribe and not Zenoh's queryable + `get`: a registrar's messages are
one-way (`StatusNotice`, `Unload`, ... want no answer; a `Load` is answered when its
load is done, possibly minutes later), and an answer is just another one-way message
back. A `get` would hold a Zenoh query open (and bounded by its own timeout) for as long
as a load runs, and its answers would come on Zenoh's threads. With puts, every message
is a frame of the AF_UNIX carrier (`codec.frame`: token + pickle; the reply stays with
the sender under the token) behind a small header (`zenoh_wire`), and the failure of a
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

Threads: Zenoh's callbacks never block. Each process decodes on one thread per sending
process and kind (messages, answers: a held answer never holds up a notice); a frame
flagged plain (`zenoh_wire.PLAIN`: builtin data and wire records, whose unpickling runs
no user code) is decoded on Zenoh's thread itself when nothing of its sender waits before
it (one thread hop less per message; a dedup-hit call measured 1.8-1.9x a raw Zenoh
`get` on loopback). It sends from one writer thread per destination (a registrar's key for
requests, a process's answer key for answers), so a sender never blocks on a peer, no
answer is sent on an actor thread, and messages from one process to one registrar keep
their order (one writer, one Zenoh route, one decode thread). Puts are reliable and
block on a full queue (`CongestionControl.BLOCK`) on the writer thread only; Zenoh closes
a link that stays blocked longer than half the lease.

Presence (liveliness tokens, one presence thread applies them in order):

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
  (`rr/<s>/ping/<zid>`): its token may be back before what is put to it gets through.

One name, one server: `serve` first declares a claim token, then asks the network for
servers and claims of the name. A server of another process is a `DuplicateNameError`;
of two claims that see each other the lower Zenoh id wins; a claim that sees a higher
one waits until that one either serves (then it yields) or withdraws. A claim is held
until the registrar's token is declared, so a rival never sees it go before the token
comes. (The router orders declarations and queries, so of two claims at least one sees
the other.)
"""

from __future__ import annotations

import collections
import contextlib
import functools
import itertools
import logging
import pickle
import re
import struct
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from rr_actors._core.directory import DIRECTORY, Peer, Reply
from rr_actors._core.replies import FutureReply, wait
from rr_actors._transport.base import Address, Endpoint
from rr_actors._transport.codec import NO_REPLY, Run, frame, payload_size, plain, what
from rr_actors._transport.inbound import _AnswerReply
from rr_actors._transport.writer import Lost, run_lost
from rr_actors._transport.zenoh_wire import (
    ANSWER,
    MESSAGE,
    VERSION,
    Header,
    header,
    parse,
    payload_of,
    versions_text,
)
from rr_actors.errors import (
    ConfigError,
    DuplicateNameError,
    InternalError,
    MessageTooLargeError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    TransferError,
    UnknownRegistrarError,
    UnknownServerError,
    _known_names,
)

__all__ = ["ZenohMember"]

logger = logging.getLogger("rr_actors")

ASK_TIMEOUT = 1.0
"""Seconds a miss of `resolve` (or `serve`'s check for the name) asks the network."""
CLAIM_TIMEOUT = 5.0
"""Seconds `serve` waits for a rival claim of the same name to serve or withdraw."""
HEAL_TIMEOUT = 2.0
"""Seconds the first message to a process back from a healed link waits for its answer
to a ping (then it is sent anyway)."""

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.\-]*")

_NO_WAITING = threading.local()
"""`active` on threads that must not wait on the network: Zenoh's callback threads (a
frame decoded there, and what its reply's continuation sends) and the presence thread."""


class _Queue:
    """Items handled one at a time in order: by its thread (started at the first item), or
    at once by the caller of `handle_now` when nothing waits before it."""

    def __init__(self, name: str, handle: Callable[[Any], None]) -> None:
        self._name = name
        self._handle = handle
        self._cond = threading.Condition(threading.Lock())
        self._items: collections.deque[Any] = collections.deque()
        self._started = False
        self._busy = False  # an item is being handled (by the thread or a caller)
        self.closed = False

    def put(self, item: Any) -> bool:
        """Queue `item` for the thread; False if the queue is closed."""
        with self._cond:
            if self.closed:
                return False
            self._items.append(item)
            if not self._started:
                self._started = True
                threading.Thread(target=self._run, name=self._name, daemon=True).start()
            else:
                self._cond.notify()
            return True

    def handle_now(self, item: Any) -> bool:
        """Handle `item` on the calling thread if nothing is queued or being handled (then
        it keeps its order); False (nothing done) otherwise."""
        with self._cond:
            if self.closed or self._busy or self._items:
                return False
            self._busy = True
        try:
            self._handle(item)
        except Exception:
            logger.exception("%s: handling an item failed", self._name)
        finally:
            with self._cond:
                self._busy = False
                if self._items:
                    self._cond.notify()
        return True

    def finish(self) -> None:
        """Take no more items; the thread handles those queued, then ends."""
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def close(self) -> list[Any]:
        """Stop; the items not yet handled are returned."""
        with self._cond:
            self.closed = True
            left = list(self._items)
            self._items.clear()
            self._cond.notify_all()
            return left

    def _run(self) -> None:
        while True:
            with self._cond:
                while (self._busy or not self._items) and not (self.closed and not self._items):
                    self._cond.wait()
                if not self._items:
                    return
                item = self._items.popleft()
                self._busy = True
            try:
                self._handle(item)
            except Exception:
                logger.exception("%s: handling an item failed", self._name)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()


class _Outbox:
    """The writer of one destination key: its thread puts payloads in the order sent."""

    def __init__(
        self, session: zenoh.Session, key: str, ready: Callable[[], None] | None = None
    ) -> None:
        self.key = key
        self._ready = ready  # runs on the writer thread before the first put
        self._publisher = session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self._queue = _Queue(f"rr-zput-{key.rsplit('/', 1)[-1]}", self._put)

    @property
    def closed(self) -> bool:
        return self._queue.closed

    def send(self, data: bytes, on_lost: Lost | None = None) -> bool:
        """Queue `data`; False (nothing sent) if the outbox is closed."""
        return self._queue.put((data, on_lost))

    def _put(self, item: tuple[bytes, Lost | None]) -> None:
        data, on_lost = item
        ready, self._ready = self._ready, None
        if ready is not None:
            ready()
        try:
            self._publisher.put(data)
        except Exception as exc:  # noqa: BLE001 - the session closed: the frame is lost
            logger.debug("a put on %s failed: %s", self.key, exc)
            if on_lost is not None:
                run_lost([on_lost])

    def close(self) -> None:
        """Stop sending: what is still queued is lost (its `on_lost` runs)."""
        lost = [on_lost for _, on_lost in self._queue.close() if on_lost is not None]
        with contextlib.suppress(Exception):
            self._publisher.undeclare()  # type: ignore[no-untyped-call]
        run_lost(lost)


class _Waiting:
    __slots__ = ("limit", "message", "name", "reply")

    def __init__(self, name: str, reply: Reply, message: Any, limit: int) -> None:
        self.name = name
        self.reply = reply
        self.message = message
        self.limit = limit


class _Server:
    """A registrar of another process as its liveliness token says."""

    __slots__ = ("limit", "supervisor", "zid")

    def __init__(self, zid: str, supervisor: str, limit: int) -> None:
        self.zid = zid
        self.supervisor = supervisor
        self.limit = limit


class _Local:
    """A registrar served by this process: its subscriber and token."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.name = endpoint.name
        self.max_message_bytes = endpoint.max_message_bytes
        self.subscriber: Any = None
        self.token: Any = None
        self.lock = threading.Lock()
        self.ended = False


class _AnswerLink:
    """Where the stand-in reply (`inbound._AnswerReply`) of one message sends its answer."""

    __slots__ = ("listener", "member", "plain", "sender")

    def __init__(self, member: ZenohMember, sender: str, listener: _Local) -> None:
        self.member = member
        self.sender = sender
        self.listener = listener
        self.plain = False

    def send(self, data: bytes, on_lost: Lost | None = None) -> bool:
        return self.member._answer_to(self.sender, data, on_lost, plain=self.plain)


class _Answer(_AnswerReply):
    """The stand-in reply of a message that came over Zenoh: marks plain answers."""

    __slots__ = ()

    def set_result(self, value: Any) -> None:
        self._link.plain = plain(value)  # type: ignore[attr-defined]
        super().set_result(value)


class ZenohPeer:
    """A registrar of another process of the system, reached over Zenoh."""

    def __init__(self, member: ZenohMember, name: str) -> None:
        self.name = name
        self._member = member

    def tell(self, message: Any) -> None:
        """Send `message`; its reply (if any) is answered later. Never blocks on the peer.

        Raises:
            ConfigError: the message cannot be pickled.
            MessageTooLargeError: pickled, it is over the registrar's `max_message_bytes`.
            RegistrarUnavailableError: its process is gone or cannot be reached.
            RegistrarStoppedError: it was stopped, or this process left the system.
        """
        self._member._send(self.name, message)

    def run(self, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """Run `fn(registrar)` in the registrar's process; return its result."""
        reply = FutureReply()
        try:
            self.tell(Run(fn, reply))
        except RrError as exc:
            reply.set_error(exc)
        return wait(reply.future, timeout, f"run() on registrar {self.name!r}")


class ZenohMember:
    """This process's membership of a system over an open Zenoh session.

    Args:
        system: the system's name (every key starts with `rr/<system>/`).
        session: the open session (router or client mode).
        speakers: the Zenoh ids of the processes `supervised_by` can name, by pid (the
            router of this host, for a process that attached through it).
        on_close: called once the member closed.
    """

    def __init__(
        self,
        system: str,
        session: zenoh.Session,
        *,
        speakers: dict[int, str] | None = None,
        on_close: Callable[[], None] | None = None,
    ) -> None:
        self.system = system
        self.zid = str(session.zid())
        self.closed = False
        self._session = session
        self._speakers = dict(speakers or {})
        self._supervisor: str | None = None  # set by `supervised_by`: nobody until then
        self._on_close = on_close
        self._address: Address | None = None
        self._prefix = f"rr/{system}"
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        # presence, as the liveliness tokens say (the presence thread writes it)
        self._seq = 0
        self._deleted: dict[str, int] = {}  # token key -> seq of its last deletion
        self._procs: set[str] = set()
        self._vanished: set[str] = set()  # processes whose token went at least once
        self._servers: dict[str, dict[str, _Server]] = {}
        self._claims: dict[str, set[str]] = {}
        self._stopped: set[tuple[str, str]] = set()
        self._gone: dict[str, str] = {}  # name -> "stopped" | "died"
        self._last: dict[str, str] = {}  # name -> the Zenoh id of its last server
        self._awaiting: dict[str, str] = {}  # name -> its supervisor: lost if that one goes
        # this process's side
        self._locals: dict[str, _Local] = {}
        self._stop_marks: dict[str, Any] = {}
        self._peers: dict[str, ZenohPeer] = {}
        self._waiting: dict[int, _Waiting] = {}
        self._tokens = itertools.count(1)
        self._outboxes: dict[str, _Outbox] = {}
        self._inboxes: dict[tuple[str, int], _Queue] = {}
        self._warned: set[str] = set()
        self._presence = _Queue("rr-zpresence", self._apply)
        self._answers = session.declare_subscriber(
            f"{self._prefix}/ans/{self.zid}", self._on_answer
        )
        self._live = session.liveliness().declare_subscriber(
            f"{self._prefix}/live/**", self._on_live, history=True
        )
        self._pings = session.declare_queryable(
            f"{self._prefix}/ping/{self.zid}", lambda query: query.reply(query.key_expr, b"")
        )
        self._proc_token = session.liveliness().declare_token(
            f"{self._prefix}/live/proc/{self.zid}"
        )
        DIRECTORY.add_resolver(self.resolve, self.names)

    # -- the Transport interface ---------------------------------------------------------

    @property
    def address(self) -> Address:
        """What other processes of this host join through (the router's address)."""
        assert self._address is not None
        return self._address

    def resolve(self, name: str) -> Peer | None:
        """A peer for registrar `name` of another process of this system.

        A name not seen yet is asked of the network (at most `ASK_TIMEOUT` seconds).

        Raises:
            UnknownRegistrarError: nobody serves `name` on this system (the message names
                the system).
        """
        if self.closed or name in self._locals:
            return None  # served here: the directory's own record says stopped or died
        known = bool(self._servers.get(name))  # (served elsewhere now: before a local record)
        if not known and not isinstance(DIRECTORY.gone_error(name), UnknownRegistrarError):
            return None  # a registrar of this process that stopped or died
        known = known or name in self._gone
        if not known and _NAME.fullmatch(name):
            self._ask(name)
            known = bool(self._servers.get(name))
        if not known:
            raise UnknownRegistrarError(  # the known: this process's registrars too
                f"no registrar named {name!r} on system {self.system!r}"
                + _known_names(name, DIRECTORY.names() - {name})
            )
        with self._lock:
            return self._peers.setdefault(name, ZenohPeer(self, name))

    def names(self) -> list[str]:
        """The registrars of other processes of the system that serve now."""
        if self.closed:
            return []
        return sorted(name for name, servers in list(self._servers.items()) if servers)

    def serve(self, endpoint: Endpoint) -> None:
        """Make a registrar of this process reachable (see the module docstring).

        Raises:
            DuplicateNameError: another process of the system serves that name.
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
        claim = self._session.liveliness().declare_token(
            f"{self._prefix}/live/claim/{name}/{self.zid}"
        )
        try:
            self._claim(name)
            local = _Local(endpoint)
            supervisor = self._supervisor or (
                self.zid if DIRECTORY.restart_expected(name) else "none"
            )
            local.subscriber = self._session.declare_subscriber(
                f"{self._prefix}/reg/{name}",
                lambda sample: self._on_message(local, sample),
            )
            token_key = (
                f"{self._prefix}/live/reg/{name}/{self.zid}/{supervisor}/{local.max_message_bytes}"
            )
            local.token = self._session.liveliness().declare_token(token_key)
        finally:  # after the token: a rival sees this one serve before the claim goes
            claim.undeclare()  # type: ignore[no-untyped-call]
        with self._lock:
            self._locals[name] = local
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

    def close(self) -> None:
        """Leave the system: stop serving, fail what waits, close the session."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            locals_ = list(self._locals.values())
        DIRECTORY.remove_resolver(self.resolve)
        for local in locals_:
            self._unserve(local, stopped=local.endpoint.stopped_cleanly())
        self._fail_waiting(lambda _w: True, RegistrarStoppedError("this process left the system"))
        with self._lock:
            outboxes = list(self._outboxes.values())
            inboxes = list(self._inboxes.values())
        for outbox in outboxes:
            outbox.close()
        for inbox in inboxes:
            inbox.close()
        self._presence.close()
        with contextlib.suppress(Exception):
            self._session.close()  # type: ignore[no-untyped-call]
        if self._on_close is not None:
            self._on_close()

    # -- serving ---------------------------------------------------------------------------

    def _claim(self, name: str) -> None:
        """With this process's claim on `name` declared: return once it may serve it.

        Raises:
            DuplicateNameError: another process serves it, or claims it and wins.
        """
        me = int(self.zid, 16)
        self._ask(name)
        deadline = time.monotonic() + CLAIM_TIMEOUT
        with self._changed:
            while True:
                others = [z for z in self._servers.get(name, {}) if z != self.zid]
                if others:
                    raise DuplicateNameError(
                        f"a registrar named {name!r} is already served on system "
                        f"{self.system!r} (by process {others[0]})"
                    )
                rivals = [z for z in self._claims.get(name, ()) if z != self.zid]
                if any(int(z, 16) < me for z in rivals):
                    raise DuplicateNameError(
                        f"another process of system {self.system!r} starts a registrar "
                        f"named {name!r} at the same time, and wins the tie-break"
                    )
                if not rivals:
                    return
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DuplicateNameError(
                        f"another process of system {self.system!r} is starting a "
                        f"registrar named {name!r}"
                    )
                self._changed.wait(left)

    def _barrier(self, key: str) -> None:
        """Return once the router this process talks to has seen the token `key`.

        A query after a declaration reaches the router after it (one link, in order), so
        its answer means other processes resolving the name find it.
        """
        with contextlib.suppress(Exception):
            for _reply in self._session.liveliness().get(key, timeout=ASK_TIMEOUT):
                pass

    def _watch(self, local: _Local) -> None:
        local.endpoint.wait_ended()
        self._unserve(local, stopped=local.endpoint.stopped_cleanly())

    def _unserve(self, local: _Local, *, stopped: bool) -> None:
        """Stop serving `local`; a clean stop is marked before the token goes."""
        with local.lock:
            if local.ended:
                return
            local.ended = True
            if stopped:  # the mark goes out before the token: peers say "stopped"
                with contextlib.suppress(Exception):
                    self._stop_marks[local.name] = self._session.liveliness().declare_token(
                        f"{self._prefix}/live/stopped/{local.name}/{self.zid}"
                    )
            with contextlib.suppress(Exception):
                local.token.undeclare()
            with contextlib.suppress(Exception):
                local.subscriber.undeclare()
        with self._lock:
            if self._locals.get(local.name) is local:
                del self._locals[local.name]

    # -- sending ---------------------------------------------------------------------------

    def _server(self, name: str) -> _Server | None:
        servers = self._servers.get(name)
        if not servers:
            return None
        for server in list(servers.values()):
            return server
        return None

    def _gone_error(self, name: str) -> RrError:
        if self.closed:
            return RegistrarStoppedError("this process left the system")
        if self._gone.get(name) == "stopped":
            return RegistrarStoppedError(f"registrar {name!r} was stopped")
        return RegistrarUnavailableError(
            f"registrar {name!r} of system {self.system!r} cannot be reached (its process "
            f"died or its link is down)"
        )

    def _send(self, name: str, message: Any) -> None:
        reply: Reply | None = getattr(message, "reply", None)
        if reply is not None:
            message = message.detached()
        token = next(self._tokens) if reply is not None else NO_REPLY
        try:
            data = frame(token, message)
        except BaseException as exc:  # (a SystemExit from a user __reduce__ is contained too)
            raise ConfigError(f"{what(message, name)} is not picklable: {exc}") from exc
        server = self._server(name)
        if server is None and not self.closed:  # maybe served again, not yet heard here
            self._ask(name)
            server = self._server(name)
        if server is None:
            raise self._gone_error(name)
        size = payload_size(data)
        if size > server.limit:
            raise MessageTooLargeError(
                f"the {what(message, name)} is {size} bytes pickled, over registrar "
                f"{name!r}'s max_message_bytes ({server.limit}); nothing was sent",
                size,
                server.limit,
            )
        if reply is not None:
            self._waiting[token] = _Waiting(name, reply, message, server.limit)
        outbox = self._outbox(f"{self._prefix}/reg/{name}", server.zid)
        sent = (  # (gone meanwhile: its presence may have missed this reply)
            self._server(name) is not None
            and outbox is not None
            and outbox.send(header(MESSAGE, self.zid, plain=plain(message)) + data)
        )
        if not sent and (reply is None or self._waiting.pop(token, None) is not None):
            raise self._gone_error(name)

    def _outbox(self, key: str, zid: str | None = None) -> _Outbox | None:
        """The outbox of `key`, whose subscriber is in process `zid` (if known)."""
        outbox = self._outboxes.get(key)
        if outbox is not None and not outbox.closed:
            return outbox
        if self.closed:
            return None
        healed = zid is not None and zid in self._vanished
        ready = functools.partial(self._until_answered, zid) if healed else None
        fresh = _Outbox(self._session, key, ready)  # (no Zenoh call under our lock: its
        with self._lock:  # callbacks take it)
            outbox = self._outboxes.get(key)
            if outbox is None or outbox.closed:
                self._outboxes[key] = outbox = fresh
        if outbox is not fresh:
            fresh.close()
        return outbox

    def _until_answered(self, zid: str | None) -> None:
        """Ping process `zid` until it answers (at most `HEAL_TIMEOUT` s; writer thread).

        After a healed link its tokens may be back here before what is sent to it gets
        through: a message put in between was lost without a word (a call right after
        the heal waited for its timeout). An answered ping went the way the next put goes.
        """
        deadline = time.monotonic() + HEAL_TIMEOUT
        pause = threading.Event()
        while not self.closed and time.monotonic() < deadline:
            try:
                replies = self._session.get(f"{self._prefix}/ping/{zid}", timeout=0.25)
                if any(reply.ok is not None for reply in replies):
                    return
            except Exception:  # noqa: BLE001 - the session closed: the put fails too
                return
            pause.wait(0.01)  # (no queryable seen yet: a get returns at once)

    def _answer_to(
        self, sender: str, data: bytes, on_lost: Lost | None, *, plain: bool = False
    ) -> bool:
        """Send an answer frame to process `sender`; False if it is gone (not sent).

        (A sender whose token has not been seen yet is not gone: its message may overtake
        its token on the way through this process's threads.)
        """
        if sender in self._vanished and sender not in self._procs:
            return False
        outbox = self._outbox(f"{self._prefix}/ans/{sender}", sender)
        head = header(ANSWER, self.zid, plain=plain)
        return outbox is not None and outbox.send(head + data, on_lost)

    # -- receiving (Zenoh's callbacks queue; one thread per sending process decodes) ------

    def _receive(self, head: Header, kind: int, item: Any) -> None:
        """Hand `item` to the decode thread of (sender, `kind`) (Zenoh's callbacks).

        A plain frame (`zenoh_wire.PLAIN`: unpickling it runs no user code) of our version
        is decoded here at once when nothing of that sender waits before it.
        """
        sender = head.sender
        for _attempt in (1, 2):  # (its inbox may have just finished: the sender went)
            inbox = self._inboxes.get((sender, kind))
            if inbox is None or inbox.closed:
                handle = self._deliver if kind == MESSAGE else self._answered
                with self._lock:
                    if self.closed:
                        return
                    inbox = self._inboxes.get((sender, kind))
                    if inbox is None or inbox.closed:
                        inbox = _Queue(f"rr-zread-{sender[:8]}-{kind}", handle)
                        self._inboxes[(sender, kind)] = inbox
            if head.plain and head.ours and inbox.handle_now(item):
                return
            if inbox.put(item):
                return

    def _on_message(self, local: _Local, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            _NO_WAITING.active = True
            self._receive(head, MESSAGE, (local, data, head))

    def _on_answer(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            _NO_WAITING.active = True
            self._receive(head, ANSWER, (data, head))

    def _deliver(self, item: tuple[_Local, bytes, Header]) -> None:
        """Decode one message for a registrar of this process and tell it (decode thread)."""
        local, data, head = item
        name = local.name
        token, payload = payload_of(data, head)
        if not head.ours:
            self._refuse_version(name, head, token)
            return
        if len(payload) > local.max_message_bytes:
            too_large = MessageTooLargeError(
                f"a message of {len(payload)} bytes for registrar {name!r} is over its "
                f"max_message_bytes ({local.max_message_bytes}); it was not read",
                len(payload),
                local.max_message_bytes,
            )
            logger.warning("%s", too_large)
            if token != NO_REPLY:
                self._answer_to(head.sender, frame(token, (None, too_large)), None)
            return
        try:
            message = pickle.loads(payload)
        except BaseException as exc:  # noqa: BLE001 - answered as an error, never raised here
            if token != NO_REPLY:
                unreadable = TransferError(
                    f"a message for registrar {name!r} cannot be unpickled: {exc}"
                )
                self._answer_to(head.sender, frame(token, (None, unreadable)), None)
            return
        reply = None
        if token != NO_REPLY:
            if not hasattr(message, "reply"):
                error: RrError = InternalError(
                    f"a {type(message).__name__} message for registrar {name!r} cannot be answered"
                )
                self._answer_to(head.sender, frame(token, (None, error)), None)
                return
            reply = _Answer(_AnswerLink(self, head.sender, local), token, message)  # type: ignore[arg-type]
            object.__setattr__(message, "reply", reply)
        if type(message) is Run:
            self._run(local, message)
            return
        try:
            DIRECTORY.lookup(name).tell(message)
        except Exception as exc:
            if reply is None:
                raise
            reply.set_error(exc if isinstance(exc, RrError) else RrError(f"{exc!r}"))

    def _refuse_version(self, name: str, head: Header, token: int) -> None:
        """A message of another version: not unpickled; its sender is told why."""
        if head.sender not in self._warned:
            self._warned.add(head.sender)
            logger.warning(
                "registrar %s refused a message of process %s: %s; pickles do not cross "
                "versions, so nothing of it was read",
                name,
                head.sender,
                versions_text(head),
            )
        if token != NO_REPLY:
            outbox = self._outbox(f"{self._prefix}/ans/{head.sender}")
            if outbox is not None:
                outbox.send(
                    header(VERSION, self.zid) + struct.pack("!i", 8) + struct.pack("<Q", token)
                )

    def _run(self, local: _Local, message: Run) -> None:
        reply = message.reply
        assert reply is not None

        def task() -> None:
            try:
                result = local.endpoint.run(message.fn)
            except BaseException as exc:  # noqa: BLE001 - the caller gets it
                reply.set_error(exc)
            else:
                reply.set_result(result)

        threading.Thread(target=task, name=f"rr-zrun-{local.name}", daemon=True).start()

    def _answered(self, item: tuple[bytes, Header]) -> None:
        """Decode one answer and resolve the reply waiting for it (decode thread)."""
        data, head = item
        token, payload = payload_of(data, head)
        waiting = self._waiting.pop(token, None)
        if waiting is None:
            return
        if head.kind == VERSION or not head.ours:
            waiting.reply.set_error(
                TransferError(
                    f"registrar {waiting.name!r} runs another version ({versions_text(head)}): "
                    f"pickles do not cross versions, so the {what(waiting.message, waiting.name)}"
                    f" was not read there"
                )
            )
            return
        if len(payload) > waiting.limit:
            self._compensate(waiting)
            waiting.reply.set_error(
                MessageTooLargeError(
                    f"the answer to the {what(waiting.message, waiting.name)} is "
                    f"{len(payload)} bytes pickled, over registrar {waiting.name!r}'s "
                    f"max_message_bytes ({waiting.limit})",
                    len(payload),
                    waiting.limit,
                )
            )
            return
        try:
            value, error = pickle.loads(payload)
        except BaseException as exc:  # noqa: BLE001 - any unpickling failure fails this answer
            self._compensate(waiting)
            failure: RrError = waiting.message.unreadable_answer(waiting.name, exc)
            failure.__cause__ = exc
            waiting.reply.set_error(failure)
            return
        if error is None:
            waiting.reply.set_result(value)
        elif isinstance(error, BaseException):
            waiting.reply.set_error(error)
        else:
            waiting.reply.set_error(
                InternalError(f"a malformed answer from registrar {waiting.name!r}")
            )

    def _compensate(self, waiting: _Waiting) -> None:
        """The caller gets an error instead of the answer: undo what handling it created."""
        compensation = waiting.message.compensation()
        if compensation is not None:
            with contextlib.suppress(RrError):
                self._send(waiting.name, compensation)

    def _fail_waiting(self, which: Callable[[_Waiting], bool], error: RrError) -> None:
        for token in [t for t, w in list(self._waiting.items()) if which(w)]:
            waiting = self._waiting.pop(token, None)  # atomic: the decode thread pops too
            if waiting is not None:
                waiting.reply.set_error(error)

    # -- presence ----------------------------------------------------------------------------

    def _on_live(self, sample: zenoh.Sample) -> None:
        self._presence.put((sample.kind == zenoh.SampleKind.PUT, str(sample.key_expr), None))

    def _ask(self, name: str) -> None:
        """Ask the network for the tokens of `name` (bounded) and apply what it answers.

        An answer for a token whose deletion was seen after the question was asked is
        stale and left out.
        """
        if getattr(_NO_WAITING, "active", False):
            return  # (on Zenoh's or the presence thread: what the tables say must do)
        with self._lock:
            asked_at = self._seq
        keys: list[str] = []
        with contextlib.suppress(Exception):
            replies = self._session.liveliness().get(
                f"{self._prefix}/live/*/{name}/**", timeout=ASK_TIMEOUT
            )
            keys.extend(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)
        done = threading.Event()
        for key in keys:
            self._presence.put((True, key, asked_at))
        self._presence.put((None, "", done))
        done.wait(ASK_TIMEOUT)

    def _apply(self, item: tuple[bool | None, str, Any]) -> None:
        """Apply one liveliness event (the presence thread): tables, then what follows."""
        _NO_WAITING.active = True
        put, key, extra = item
        if put is None:  # a marker: everything queued before it was applied
            extra.set()
            return
        parts = key.removeprefix(self._prefix + "/live/").split("/")
        with self._changed:
            self._seq += 1
            if put and extra is not None and self._deleted.get(key, -1) > extra:
                return  # a stale answer of `_ask`
            if not put:
                self._deleted[key] = self._seq
            actions = self._change(put, parts)
            self._changed.notify_all()
        for action in actions:
            action()

    def _change(self, put: bool, parts: list[str]) -> list[Callable[[], None]]:
        """Apply one event to the tables (holding the lock); what to do after."""
        kind = parts[0]
        if kind == "proc" and len(parts) == 2 and parts[1] != self.zid:
            return self._process_event(put, parts[1])
        if kind == "reg" and len(parts) == 5 and parts[2] != self.zid:
            return self._server_event(put, parts[1], _Server(parts[2], parts[3], int(parts[4])))
        if kind == "claim" and len(parts) == 3:
            claims = self._claims.setdefault(parts[1], set())
            if put:
                claims.add(parts[2])
            else:
                claims.discard(parts[2])
        elif kind == "stopped" and len(parts) == 3:
            if put:
                self._stopped.add((parts[1], parts[2]))
            else:
                self._stopped.discard((parts[1], parts[2]))
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
        actions: list[Callable[[], None]] = [functools.partial(self._lost, n) for n in lost]
        answers = self._outboxes.pop(f"{self._prefix}/ans/{zid}", None)
        if answers is not None:
            actions.append(answers.close)
        for kind in (MESSAGE, ANSWER):  # what it sent before it went is still delivered
            inbox = self._inboxes.pop((zid, kind), None)
            if inbox is not None:
                actions.append(inbox.finish)
        return actions

    def _server_event(self, put: bool, name: str, server: _Server) -> list[Callable[[], None]]:
        """A server's token of registrar `name` came or went."""
        servers = self._servers.setdefault(name, {})
        zid = server.zid
        if put:
            if zid in servers:
                return []
            servers[zid] = server
            self._gone.pop(name, None)
            self._awaiting.pop(name, None)
            if self._last.get(name) == zid and zid in self._vanished:
                return [functools.partial(self._reachable, name)]  # a healed link
            return []
        if servers.pop(zid, None) is None or servers:
            return []  # unknown, or a rival that yielded: another one serves
        stopped = (name, zid) in self._stopped
        self._gone[name] = "stopped" if stopped else "died"
        self._last[name] = zid
        error = self._gone_error(name)
        actions: list[Callable[[], None]] = [
            functools.partial(self._fail_waiting, lambda w: w.name == name, error)
        ]
        outbox = self._outboxes.pop(f"{self._prefix}/reg/{name}", None)
        if outbox is not None:
            actions.append(outbox.close)
        if stopped:
            return actions
        supervisor = server.supervisor
        if supervisor == "none" or (supervisor != self.zid and supervisor not in self._procs):
            actions.append(functools.partial(self._lost, name))
        else:
            self._awaiting[name] = supervisor  # lost if its supervisor goes too
        return actions

    def _lost(self, name: str) -> None:
        """Registrar `name` is gone for good: every endpoint served here hears it."""
        logger.info("registrar %s of system %s is lost (nobody restarts it)", name, self.system)
        for local in list(self._locals.values()):
            if local.name != name:
                local.endpoint.peer_lost(name)

    def _reachable(self, name: str) -> None:
        """Registrar `name` is back from the same process (a healed link)."""
        logger.info("registrar %s of system %s is reachable again", name, self.system)
        for local in list(self._locals.values()):
            if local.name != name:
                local.endpoint.peer_reachable(name)
