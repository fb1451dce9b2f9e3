"""The messenger: what every carrier does with a name and a message, written once.

A carrier moves frames and reports who comes and goes; the rest (naming, the `Remote`
peer, reply tokens, size limits, compensation, a served registrar's end and yield) is
here, as xoscar's above its `Channel`. The one protocol a carrier keeps (`Carrier`):

```
 resolve(name) ─► carrier.knows(name) ─► a Remote(carrier, name)
 Remote.tell ─► encode ─► carrier.route(name): a Route (limit, pending, again) ─► size
   checked, reply expected ─► carrier.send(route, frame), or its error (again: once more)
 serve(endpoint) ─► carrier.serve(endpoint): a Listening ─► its end: carrier.unserve
 the carrier's thread ─► Messenger.message ─► StandIn ─► carrier.answer(process, frame)
 the carrier's thread ─► route.pending.answered / fail; Messenger.lost / reachable
 served_elsewhere, this one kept (rule 22) ─► carrier.send(carrier.route(name, rival), Claim)
 names() ─► carrier.names()        close() ─► carrier.leave()
```

Flow: docs/explanation/architecture.md ("The messenger and its links"); contract:
docs/explanation/failure-semantics.md ("What every carrier keeps").
"""

from __future__ import annotations

import contextlib
import datetime
import itertools
import logging
import pickle
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

from rr_actors._core import runtime
from rr_actors._core.directory import DIRECTORY, Peer, Reply
from rr_actors._core.hlc import seconds
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import FutureReply, wait
from rr_actors._transport.codec import NO_REPLY, Claim, Run, frame, payload_size, what
from rr_actors._transport.resolve import FIRST_SERVED, Resolution, Sided
from rr_actors.errors import (
    CallTimeoutError,
    ConfigError,
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

logger = logging.getLogger("rr_actors")

_GONE = (RegistrarStoppedError, RegistrarUnavailableError, UnknownRegistrarError)

Lost = Callable[[], None]
"""Called (on any thread) when a queued frame could not be sent: the link ended."""

Tell = Callable[[Any], object]  # tells a compensation to the registrar an answer came from


class Endpoint(Protocol):
    """A registrar served here (`_registrar/life.py`'s `Served`); `peer_*` return at once."""

    @property
    def name(self) -> str: ...
    @property
    def max_message_bytes(self) -> int: ...  # pickled, from another process, both ways
    def run(self, fn: Callable[[Any], Any]) -> Any: ...  # `fn(registrar)` on this thread
    def wait_ended(self, timeout: float | None = None) -> bool: ...
    def stopped_cleanly(self) -> bool: ...  # (its owner stopped it: not a crash)
    def listening(self) -> None: ...  # served now: other processes can reach it
    def peer_lost(self, name: str) -> None: ...  # gone for good (rule 19)
    def peer_reachable(self, name: str) -> None: ...  # a healed link (rule 20)
    def yield_name(self, reason: str) -> None: ...  # another's server is kept (rule 22)
    def keep_name(self, reply: Reply) -> None: ...  # the kept one went: serve on? (rule 22)


class Address(Protocol):
    """Pickles; `attach()` joins the same system in another process (idempotent)."""

    def attach(self) -> Messenger: ...


class Carrier(Protocol):
    """What a carrier does for its messenger: it moves frames and reports who comes and goes
    (to `Messenger.message`, `Replies`, `lost`, `reachable`, `served_elsewhere`); the rest
    is the messenger's. Eight members; only `knows`, `route` (off an actor's thread) and
    `serve` may wait on the network, bounded."""

    def knows(self, name: str) -> bool:
        """Whether `name` is served elsewhere, or was (any thread). Raises as `resolve`."""

    def route(self, name: str, server: Sided | None = None) -> Route:
        """The way to registrar `name` now (any thread; on an actor's, never waits on the
        network), or to its server `server` (rule 22: one of two it sees; `_claim`).
        Raises why it cannot be reached (`RegistrarUnavailableError`, ...)."""

    def send(self, route: Route, data: bytes) -> None:
        """Send frame `data` over `route`, in order (never blocks). Raises why nothing of
        it left (the route went: `RegistrarUnavailableError`, `RegistrarStoppedError`)."""

    def answer(self, process: Any, data: bytes, on_lost: Lost | None) -> bool:
        """Send an answer frame back to `process`, the sender `Messenger.message` was told
        of (never blocks); False if it is gone. `on_lost()` if it goes before it leaves."""

    def serve(self, endpoint: Endpoint) -> Listening:
        """Take frames for `endpoint` (to `Messenger.message`), returning once other
        processes can find it (caller's thread). Raises as `Messenger.serve`."""

    def unserve(self, listening: Listening, *, stopped: bool) -> None:
        """Stop taking frames for `listening` (once; any thread); `stopped`: cleanly, so
        senders then get `RegistrarStoppedError`."""

    def names(self) -> list[str]: ...  # the registrars it can reach now (any thread)
    def leave(self) -> None: ...  # fail what waits, end its threads, close what it opened


class Route:
    """The messenger's record of a way to one registrar, made by its carrier (`route`):
    the registrar's `limit` (its max_message_bytes, both ways), the replies `pending`
    over it, and whether a send that failed may be tried `again` over a fresh route."""

    __slots__ = ("again", "limit", "pending")

    def __init__(self, limit: int, pending: Replies | None = None, *, again: bool = False) -> None:
        self.limit = limit
        self.pending = Replies() if pending is None else pending
        self.again = again


class Listening:
    """A registrar here as its carrier serves it (`serve`); stopped once (`unserve`,
    holding `lock`). `failing_since` (monotonic; set by the carrier): since when it has
    been unable to take new connections, and why (`failure`)."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.name = endpoint.name
        self.lock = runtime.Lock()
        self.ended = self.yielded = False
        self.yield_told = runtime.Event()  # its registrar was told to yield (`give_way`)
        self.failing_since: float | None = None
        self.failure = ""


def when(stamp: int) -> str:
    """A registration stamp as UTC, to the microsecond (rule 22: two servers of one name)."""
    at = datetime.datetime.fromtimestamp(seconds(stamp), datetime.UTC)
    return at.strftime("%Y-%m-%d %H:%M:%S.%f UTC")


class Remote:
    """A registrar of another process as a `Peer`: told over its carrier's route."""

    __slots__ = ("carrier", "name")

    def __init__(self, carrier: Carrier, name: str) -> None:
        self.carrier = carrier
        self.name = name

    def tell(self, message: Any) -> None:
        """Send `message` (any thread; in order; never blocks). Raises as `Peer.tell`."""
        send(self, message)

    def deliver(self, message: Any) -> None:
        self.tell(message)  # (a registrar of another process never runs on this thread)

    def run(self, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """`fn(registrar)` on a fresh thread of its process. Raises as `Messenger.run`."""
        return wait(self.submit(fn).future, timeout, f"run() on registrar {self.name!r}")

    def submit(self, fn: Callable[[Any], Any]) -> FutureReply:
        """`run` without the wait: the reply's future settles with its result or error."""
        reply = FutureReply()
        try:
            self.tell(Run(fn, reply))
        except RrError as exc:
            reply.set_error(exc)
        return reply


def run_lost(callbacks: list[Lost]) -> None:
    """Run the `on_lost` of frames that did not leave, logging one that raises."""
    for on_lost in callbacks:
        try:
            on_lost()
        except Exception:
            logger.exception("cleaning up after a lost frame failed")


# -- sending ------------------------------------------------------------------------------

_TOKENS = itertools.count(1)


class Outgoing(NamedTuple):
    """A message ready to send: its reply kept under `token`, `data` its frame."""

    message: Any
    reply: Reply | None
    token: int
    data: bytes


def encode(name: str, message: Any) -> Outgoing:
    """Detach `message`'s reply (kept under a fresh token) and frame it (`ConfigError`)."""
    reply: Reply | None = getattr(message, "reply", None)
    if reply is not None:
        message = message.detached()
    token = next(_TOKENS) if reply is not None else NO_REPLY  # atomic in CPython
    try:
        data = frame(token, message)
    except BaseException as exc:  # (a SystemExit from a user __reduce__ is contained too)
        raise ConfigError(f"{what(message, name)} is not picklable: {exc}") from exc
    return Outgoing(message, reply, token, data)


def too_large(message: Any, data: bytes, name: str, limit: int) -> MessageTooLargeError | None:
    """The error if frame `data` of `message` is over registrar `name`'s `limit`."""
    size = payload_size(data)
    if size <= limit:
        return None
    return MessageTooLargeError(
        f"the {what(message, name)} is {size} bytes pickled, over registrar "
        f"{name!r}'s max_message_bytes ({limit}); nothing was sent",
        size,
        limit,
    )


def send(peer: Remote, message: Any) -> None:
    """`Remote.tell`: retried once over a fresh route if the route says `again`."""
    carrier, name = peer.carrier, peer.name
    outgoing = encode(name, message)
    reply = outgoing.reply
    for _attempt in (1, 2):
        route = carrier.route(name)
        oversized = too_large(outgoing.message, outgoing.data, name, route.limit)
        if oversized is not None:
            raise oversized
        if reply is not None:
            route.pending.expect(outgoing, peer, route.limit)
        try:
            carrier.send(route, outgoing.data)
        except RrError as exc:
            error = exc
        else:
            return
        if reply is not None and not route.pending.forget(outgoing.token):
            return  # the route's end failed the reply already
        if not route.again:
            break
    raise error


class Replies(dict[int, tuple[Reply, Any, Remote, int]]):
    """By token: `(reply, message, peer, limit)`; entries leave only by atomic dict ops."""

    __slots__ = ()

    def expect(self, outgoing: Outgoing, peer: Remote, limit: int) -> None:
        assert outgoing.reply is not None
        self[outgoing.token] = (outgoing.reply, outgoing.message, peer, limit)

    def forget(self, token: int) -> bool:
        """Stop waiting for `token`; False if it was not waited for (answered or failed)."""
        return self.pop(token, None) is not None

    def take(self, name: str | None = None) -> list[Reply]:
        """Stop waiting on registrar `name` (`None`: every one); the replies, to fail."""
        taken: list[Reply] = []
        if name is None:
            while True:
                try:
                    _, entry = self.popitem()  # atomic: the receiver pops too
                except KeyError:
                    return taken
                taken.append(entry[0])
        for token in [t for t, entry in list(self.items()) if entry[2].name == name]:
            found = self.pop(token, None)
            if found is not None:
                taken.append(found[0])
        return taken

    def fail(self, name: str | None, error: RrError | Callable[[], RrError]) -> None:
        """Fail every reply waiting on `name` (`None`: all) with `error` (or `error()`)."""
        taken = self.take(name)
        if taken and not isinstance(error, RrError):
            error = error()
        for reply in taken:
            reply.set_error(error)  # type: ignore[arg-type]

    def answered(self, token: int, payload: bytes | memoryview) -> None:
        """Resolve the reply waiting for `token` (an answer nobody waits for is dropped)."""
        entry = self.pop(token, None)
        if entry is None:
            return
        reply, message, peer, limit = entry
        if len(payload) > limit:
            answer_too_large(reply, message, peer.name, len(payload), limit, peer.tell)
            return
        answer(reply, message, peer.name, payload, peer.tell)

    def too_large(self, token: int, size: int) -> None:
        """Answer `token` was `size` bytes, over its limit: skipped unread."""
        entry = self.pop(token, None)
        if entry is not None:
            reply, message, peer, limit = entry
            answer_too_large(reply, message, peer.name, size, limit, peer.tell)

    def refused(self, token: int, versions: str) -> None:
        """Answer `token`: the message was of another version, not read."""
        entry = self.pop(token, None)
        if entry is not None:
            reply, message, peer, _limit = entry
            reply.set_error(
                TransferError(
                    f"registrar {peer.name!r} runs another version ({versions}): pickles "
                    f"do not cross versions, so the {what(message, peer.name)} was not "
                    f"read there"
                )
            )


# -- the membership: naming, receiving, what the carrier reports --------------------------


class Messenger:
    """One process's membership of a system over a carrier (the `Transport`): see
    docs/explanation/inside.md ("What the messenger does with what a carrier reports").

    Args:
        system: the system's name (the AF_UNIX carrier's runtime directory).
        resolver: whether the directory asks it for names not registered here.
        resolve: which of two servers of one name is kept after a heal (`Resolution`).

    Raises:
        ConfigError: `resolve` is not a strategy (`Resolution`).
    """

    leaves = True  # closing it closes its carrier (a simulated process's does not)

    def __init__(
        self, system: str, *, resolver: bool = True, resolve: object = "first_served"
    ) -> None:
        self.system = system
        self.resolution = FIRST_SERVED if resolve == "first_served" else Resolution(resolve)
        self.closed = False
        self.supervisor: int | None = None  # `supervised_by`'s pid
        self._resolver = resolver
        self._lock = runtime.Lock()
        self._served: dict[str, Listening] = {}
        self._yielding: dict[str, Listening] = {}  # rule 22: given way, not ended yet
        self._early: dict[str, list[Sided]] = {}  # names being served: rivals heard meanwhile
        self._peers: dict[str, Remote] = {}
        self._carrier: Carrier | None = None
        self._lookup: Callable[[str], Peer] = DIRECTORY.lookup

    @property
    def address(self) -> Address:
        """What to hand to processes that should join the same system."""
        raise NotImplementedError

    def joined(self, carrier: Carrier) -> None:
        """Its carrier is open: names not registered here are asked of it from now on."""
        self._carrier = carrier
        if self._resolver:
            DIRECTORY.add_resolver(self.resolve, self.names)

    def link(self) -> Carrier:
        """The carrier (Zenoh's opens here, at first use)."""
        carrier = self._carrier
        assert carrier is not None, "a messenger is used before its carrier joined"
        return carrier

    # -- the Transport surface -----------------------------------------------------------

    def resolve(self, name: str) -> Peer | None:
        """A peer for `name` elsewhere; `None` if served here or unknown.

        Raises `UnknownRegistrarError` (nobody serves it), `RegistrarUnavailableError`.
        """
        peer = self._peers.get(name)
        if peer is not None:
            return peer
        if self.closed or name in self._served:
            return None
        carrier = self.link()
        if not carrier.knows(name):
            return None
        with self._lock:
            return self._peers.setdefault(name, Remote(carrier, name))

    def names(self) -> list[str]:
        """The registrars of the system the carrier can reach now (any host)."""
        return [] if self.closed else self.link().names()

    def serve(self, endpoint: Endpoint) -> None:
        """Make a registrar here reachable from other processes until it ends.

        Raises `DuplicateNameError`, `ConfigError` (bad name or address),
        `RegistrarUnavailableError` (no answer in time), `RegistrarStoppedError` (left).
        """
        name = endpoint.name
        carrier = self.link()
        with self._lock:
            if self.closed:
                raise RegistrarStoppedError(f"this process left system {self.system!r}")
            old = self._served.pop(name, None)
            self._peers.pop(name, None)  # (its carrier's route to it goes: `serve`)
        if old is not None:
            self._unserve(old, stopped=False)
        with self._lock:
            self._early[name] = []
        try:
            listening = carrier.serve(endpoint)
        except BaseException:
            with self._lock:
                self._early.pop(name, None)
            raise
        with self._lock:
            early, left = self._early.pop(name, []), self.closed
            if not left:  # (a `close` while the carrier served it did not see it)
                self._served[name] = listening
        if left:
            self._unserve(listening, stopped=False)
            raise RegistrarStoppedError(f"this process left system {self.system!r}")
        for rival in early:  # (told of before it was listed)
            self.served_elsewhere(name, rival)
        runtime.Thread(
            target=self._watch_end, args=(listening,), name=f"rr-watch-{name}", daemon=True
        ).start()
        endpoint.listening()

    def run(self, name: str, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """`fn(registrar)` where registrar `name` lives (here: on this thread).

        Raises `UnknownServerError`, `CallTimeoutError` (`timeout` s),
        `RegistrarUnavailableError`, `RegistrarStoppedError`.
        """
        listening = self._served.get(name)
        if listening is not None:
            return listening.endpoint.run(fn)
        try:
            peer = self.resolve(name)
        except UnknownRegistrarError as exc:
            raise UnknownServerError(str(exc)) from None
        if not isinstance(peer, Remote):
            raise UnknownServerError(
                f"no registrar named {name!r} on system {self.system!r}"
                + _known_names(name, self.names())
            )
        return peer.run(fn, timeout=timeout)

    def serving_trouble(self, name: str) -> tuple[float, str] | None:
        """For how long (seconds) and why `name` served here cannot take new connections."""
        listening = self._served.get(name)
        since = None if listening is None else listening.failing_since
        if listening is None or since is None:
            return None
        return runtime.monotonic() - since, listening.failure

    def supervised_by(self, pid: int | None) -> None:
        """Process `pid` speaks for registrars served from now on if this one dies (rule 19)."""
        self.supervisor = pid

    def close(self) -> None:
        """Leave the system: stop serving, fail what waits, close the carrier (idempotent)."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            served = list(self._served.values())
            self._served.clear()
            self._peers.clear()
        if self._resolver:
            DIRECTORY.remove_resolver(self.resolve)
        for listening in served:
            self._unserve(listening, stopped=listening.endpoint.stopped_cleanly())
        if self._carrier is not None and self.leaves:
            self._carrier.leave()

    # -- who serves what, for the carrier ------------------------------------------------

    def serving(self, name: str) -> Listening | None:
        return self._served.get(name)

    def served(self) -> list[str]:
        return list(self._served)

    def peer(self, name: str) -> Remote | None:
        return self._peers.get(name)

    def give_way(self, listening: Listening, reason: str) -> None:
        """Another process's server of the name is kept (rule 22): stop serving, yield."""
        with listening.lock:
            if listening.ended:
                return
            listening.ended = listening.yielded = True
            with self._lock:  # (before it stops: the one kept may be lost as it does)
                self._yielding[listening.name] = listening
            self.link().unserve(listening, stopped=False)
        self._forget(listening)
        logger.error(
            "%s; this one stops serving: it unloads what it serves and stops, and its "
            "consumers reconcile with the other one (an id it does not hold is FATAL)",
            reason,
        )
        listening.endpoint.yield_name(reason)
        listening.yield_told.set()  # (a `keep_name` is told after it: `_keep`)

    def served_elsewhere(self, name: str, rival: Sided) -> None:
        """Another process serves `name` too (rule 22): give way or tell it (`_claim`)."""
        with self._lock:
            local = self._served.get(name)
            early = self._early.get(name) if local is None else None
            if early is not None:
                early.append(rival)
                return
        if not isinstance(local, Sided) or rival.who == local.who:
            return
        if self.resolution.kept(name, [local, rival]) is local:
            self._claim(name, local, rival)
            return
        self.give_way(
            local,
            f"registrar {name!r} of system {self.system!r} is served by process "
            f"{rival.who} too, since {when(rival.stamp)}, and by this one (process "
            f"{local.who}, since {when(local.stamp)}): one name is one registrar (rule "
            f"22), and resolve={self.resolution.resolve!r} keeps the other one",
        )

    def _claim(self, name: str, local: Sided, rival: Sided) -> None:
        """Tell `rival`'s process that `local` is kept (it may not hear after a one-way heal)."""
        process = local.rank[1]
        claim = Claim(name, local.who, local.stamp, process, local.side, local.members)
        carrier = self.link()
        try:  # (a carrier that sees one server a name raises: nothing sent)
            carrier.send(carrier.route(name, rival), frame(NO_REPLY, claim))
        except Exception as exc:  # noqa: BLE001 - its own presence may tell it still
            logger.debug("could not tell process %s of %s's claim: %s", rival.who, name, exc)

    def lost(self, name: str) -> None:
        """Registrar `name` is gone for good (rule 19): tell `MEMBERSHIP` and every endpoint."""
        logger.info("registrar %s of system %s is lost (nobody restarts it)", name, self.system)
        MEMBERSHIP.lost(name, by=f"the carrier of {self.system}", hearers=self._hearers())
        yielding = self._yielding.get(name)
        if yielding is not None:  # the one kept went while the one here yields (rule 22)
            runtime.Thread(
                target=self._keep, args=(yielding,), name=f"rr-keep-{name}", daemon=True
            ).start()

    def _keep(self, listening: Listening) -> None:
        """The one kept in `listening`'s place went before its yield ended (rule 22)."""
        name, endpoint = listening.name, listening.endpoint
        if not listening.yield_told.wait(5.0):  # (the give-way thread tells it next)
            return
        reply = FutureReply()
        endpoint.keep_name(reply)
        while True:  # (it answers within its `call_timeout`, the yield's bound, or ends)
            try:
                kept = wait(reply.future, 1.0, "keep_name")
                break
            except CallTimeoutError:
                if endpoint.wait_ended(0):
                    return
        if not kept:
            return  # it stops: its end tells this process's consumers (`_watch_end`)
        with self._lock:
            if self._yielding.get(name) is listening:
                del self._yielding[name]
        listening.yielded = False  # (its old watch says nothing at its end now)
        try:
            self.serve(endpoint)
        except RrError as exc:
            listening.yielded = True
            with self._lock:
                self._yielding[name] = listening
            endpoint.yield_name(
                f"registrar {name!r} of system {self.system!r} cannot be served again after "
                f"the one kept in its place went: {exc}"
            )
            return
        logger.warning(
            "registrar %s of system %s serves again: the one kept in its place went for good "
            "before its yield ended (rule 22)",
            name,
            self.system,
        )
        self.reachable(name)

    def reachable(self, name: str) -> None:
        """Registrar `name` is back (rules 20, 22): every other endpoint here hears it."""
        logger.info("registrar %s of system %s is reachable again", name, self.system)
        MEMBERSHIP.reachable(name, hearers=self._hearers())

    def forget_in_child(self) -> list[Listening]:
        """In a forked child: drop the parent's listeners (returned) and peers (no lock)."""
        self._lock = runtime.Lock()
        served = list(self._served.values())
        self._served.clear()
        self._peers.clear()
        self.supervisor = None
        return served

    def _hearers(self) -> tuple[Endpoint, ...]:
        return tuple(listening.endpoint for listening in list(self._served.values()))

    def _watch_end(self, listening: Listening) -> None:
        endpoint = listening.endpoint
        endpoint.wait_ended()
        self._unserve(listening, stopped=endpoint.stopped_cleanly())
        with self._lock:
            if self._yielding.get(listening.name) is listening:
                del self._yielding[listening.name]
        if listening.yielded:  # its name is the kept one's now: this process's consumers of
            # it reconcile with that one (rule 20), as other processes' do
            self.reachable(listening.name)

    def _unserve(self, listening: Listening, *, stopped: bool) -> None:
        """Stop serving `listening` once (a second caller waits until it is done)."""
        with listening.lock:
            if listening.ended:
                return
            listening.ended = True
            self.link().unserve(listening, stopped=stopped)
        self._forget(listening)

    def _forget(self, listening: Listening) -> None:
        with self._lock:
            if self._served.get(listening.name) is listening:
                del self._served[listening.name]

    # -- receiving -----------------------------------------------------------------------

    def message(
        self, endpoint: Endpoint, process: Any, token: int, payload: bytes | memoryview
    ) -> None:
        """Deliver one message from `process` to `endpoint` (the carrier's thread).

        Raises what telling the registrar raised if no answer is wanted (the carrier logs).
        """
        name, limit = endpoint.name, endpoint.max_message_bytes
        if len(payload) > limit:
            self.oversized(endpoint, process, token, len(payload))
            return
        try:
            message = pickle.loads(payload)
        except BaseException as exc:  # noqa: BLE001 - answered as an error, never raised here
            unreadable = TransferError(
                f"a message for registrar {name!r} cannot be unpickled: {exc}"
            )
            self._error(process, token, unreadable)
            return
        reply = None
        if token != NO_REPLY:
            if not hasattr(message, "reply"):
                kind = type(message).__name__
                error = InternalError(f"a {kind} message for registrar {name!r} cannot be answered")
                self._error(process, token, error)
                return
            carrier = self._carrier
            assert carrier is not None
            reply = StandIn(carrier, process, name, limit, token, message, self._lookup)
            object.__setattr__(message, "reply", reply)  # a fresh copy, ours to fill in
        if type(message) is Run:
            message.start(endpoint.run, f"rr-run-{name}")
            return
        if type(message) is Claim:  # rule 22: the kept one's process says so (`_claim`)
            runtime.Thread(
                target=self.served_elsewhere,
                args=(name, message),
                name=f"rr-claim-{name}",
                daemon=True,
            ).start()
            return
        try:
            self._lookup(name).deliver(message)  # (this thread may handle it: `Peer.deliver`)
        except Exception as exc:
            if reply is not None:
                reply.set_error(exc if isinstance(exc, RrError) else RrError(f"{exc!r}"))
            elif isinstance(exc, _GONE):  # no answer wanted: nobody to tell but the log
                logger.info("dropped a %s: %s", what(message, name), exc)
            else:
                raise

    def oversized(self, endpoint: Endpoint, process: Any, token: int, size: int) -> None:
        """Over `endpoint`'s limit: not read; answered with a `MessageTooLargeError`."""
        limit = endpoint.max_message_bytes
        error = MessageTooLargeError(
            f"a message of {size} bytes for registrar {endpoint.name!r} is over its "
            f"max_message_bytes ({limit}); it was not read",
            size,
            limit,
        )
        logger.warning("%s", error)
        self._error(process, token, error)

    def _error(self, process: Any, token: int, error: RrError) -> None:
        if token != NO_REPLY and self._carrier is not None:
            self._carrier.answer(process, frame(token, (None, error)), None)


Transport = Messenger
"""What the registrar, the process layer and the supervisor see of a carrier."""


class StandIn:
    """A delivered message's reply to `process`; one that does not arrive is compensated."""

    __slots__ = (
        "_carrier",
        "_done",
        "_limit",
        "_lookup",
        "_message",
        "_name",
        "_process",
        "_token",
    )

    def __init__(
        self,
        carrier: Carrier,
        process: Any,
        name: str,
        limit: int,
        token: int,
        message: Any,
        lookup: Callable[[str], Peer] = DIRECTORY.lookup,
    ) -> None:
        self._carrier = carrier  # answers go back to `process`, its sender
        self._process = process
        self._lookup = lookup
        self._name = name
        self._limit = limit
        self._token = token
        self._message = message
        self._done = False

    def set_result(self, value: Any) -> None:
        self._answer(value, None)

    def set_error(self, error: BaseException) -> None:
        self._answer(None, error)

    def _answer(self, value: Any, error: BaseException | None) -> None:
        if self._done:
            return
        self._done = True
        try:
            data = frame(self._token, (value, error))
        except BaseException as exc:  # noqa: BLE001 - any pickling failure (SystemExit from a
            # user __reduce__ too) becomes an error answer
            data = frame(self._token, (None, self._unpicklable(value, error, exc)))
            error = exc
        if payload_size(data) > self._limit:
            too_large = _too_large(self._message, self._name, payload_size(data), self._limit)
            if error is None:
                self._compensate()  # its caller gets an error
            data = frame(self._token, (None, too_large))
            error = too_large
        on_lost = self._compensate if error is None else None
        if not self._carrier.answer(self._process, data, on_lost) and on_lost is not None:
            on_lost()

    def _compensate(self) -> None:  # (the answer did not reach its caller)
        name, lookup = self._name, self._lookup
        compensate(self._message, lambda compensation: lookup(name).tell(compensation))

    def _unpicklable(self, value: Any, error: BaseException | None, exc: BaseException) -> RrError:
        if error is not None:
            return TransferError(
                f"{type(error).__qualname__}: {error} (the error itself did not pickle)"
            )
        self._compensate()  # its caller gets an error
        failure: RrError = self._message.unsendable_answer(self._name, value, exc)
        return failure


def compensate(message: Any, tell: Tell) -> None:
    """The caller of `message` gets an error instead: `tell` its `compensation()`, if any."""
    compensation = message.compensation()
    if compensation is not None:
        with contextlib.suppress(RrError):
            tell(compensation)


def _too_large(message: Any, name: str, size: int, limit: int) -> MessageTooLargeError:
    return MessageTooLargeError(
        f"the answer to the {what(message, name)} is {size} bytes pickled, over "
        f"registrar {name!r}'s max_message_bytes ({limit})",
        size,
        limit,
    )


def answer_too_large(
    reply: Reply, message: Any, name: str, size: int, limit: int, tell: Tell
) -> None:
    """An answer over `limit` was not read: `compensate`, then fail `reply`."""
    compensate(message, tell)
    reply.set_error(_too_large(message, name, size, limit))


def answer(reply: Reply, message: Any, name: str, payload: bytes | memoryview, tell: Tell) -> None:
    """Resolve `reply` with the answer `payload` (unreadable: after `compensate`)."""
    try:
        value, error = pickle.loads(payload)
    except BaseException as exc:  # noqa: BLE001 - any unpickling failure fails this answer
        compensate(message, tell)
        failure: RrError = message.unreadable_answer(name, exc)
        failure.__cause__ = exc
        reply.set_error(failure)
        return
    if error is None:
        reply.set_result(value)
    elif isinstance(error, BaseException):
        reply.set_error(error)
    else:
        reply.set_error(InternalError(f"a malformed answer from registrar {name!r}"))
