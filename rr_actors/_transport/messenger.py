"""The messenger: what every carrier does with a message, written once over a thin link.

A carrier moves frames to a name's process and back, and reports processes and servers
coming and going; everything a message needs besides is here, once for every carrier,
and the messenger drives the carrier through two small interfaces: a `Route` per
registrar reached (send a frame; it broke) and a `Link` per process (send an answer back
to the process a message came from):

```
 sending (any thread)
 Remote.tell(message) ─► send(): encode (reply kept under a token), route = peer.route()
   ├─ over route.limit? MessageTooLargeError; unpicklable? ConfigError (nothing sent)
   ├─ route.pending.expect(reply)  (`Replies`: where it waits for its answer)
   └─ route.send(frame) ──────────────────────► the carrier: to the name's process
        False (the route went): forget the reply, route.broken(), once more or
        peer.gone()
 Remote.run(fn) ─► submit(fn): tell(Run(fn, reply)) ─► wait (an event loop awaits it)

 receiving (the carrier's receiving thread calls the messenger)
 bytes for a registrar here ─► Messenger.message(endpoint, process, token, payload):
   over its limit? refused unread; unpickle; `StandIn` reply; tell the registrar
 the stand-in answers ─► pickles? over the limit? ─► link.answer_to(process, frame);
   lost on the way: the message's compensation() to the registrar (`compensate`)
 an answer ─► route.pending.answered / too_large / refused (`Replies`; too large or
   unreadable: compensate)
 a route or a server gone ─► route.pending.fail / Replies.fail(name): at once
 a registrar lost for good / reachable again ─► `tell_lost` / `tell_reachable`: the
   process's membership (`_core/membership.py`) records it and every registrar here
   hears it (rule 19, rule 20)
```

Carriers: `unix/` (a route is one connection: `_Channel`; answers go back on the
connection a message came on), `zenoh/` (a route is a registrar's key and the server
seen for it; answers go to the sender's answer key) and the in-memory double
(`rr_actors.testing.MemoryNetwork`). Each keeps only its framing, threads and presence.
Nothing here blocks on a peer: what it sends is queued or dropped by the carrier.
"""

from __future__ import annotations

import abc
import contextlib
import itertools
import logging
import pickle
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple, Protocol

from rr_actors._core.directory import DIRECTORY, Peer, Reply
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import FutureReply, wait
from rr_actors._transport.base import Endpoint
from rr_actors._transport.codec import NO_REPLY, Run, frame, payload_size, what
from rr_actors.errors import (
    ConfigError,
    InternalError,
    MessageTooLargeError,
    RegistrarStoppedError,
    RegistrarUnavailableError,
    RrError,
    TransferError,
    UnknownRegistrarError,
)

__all__ = [
    "Link",
    "Lost",
    "Messenger",
    "Outgoing",
    "Remote",
    "Replies",
    "Route",
    "StandIn",
    "run_lost",
    "send",
    "tell_lost",
    "tell_reachable",
]

logger = logging.getLogger("rr_actors")

_GONE = (RegistrarStoppedError, RegistrarUnavailableError, UnknownRegistrarError)
"""What `DIRECTORY.lookup` raises for a registrar that is not (or no longer) here."""

Lost = Callable[[], None]
"""Called (on any thread) when a queued frame could not be sent: the link ended."""

SendAnswer = Callable[[bytes, "Lost | None"], bool]
"""Sends an answer frame back to a message's sender; `on_lost` runs if it is queued and
then lost; False if the sender is gone (nothing sent)."""

Tell = Callable[[Any], object]
"""Tells a message (a compensation) to the registrar an answer came from.

Raises:
    RrError: it cannot be told (suppressed by `compensate`).
"""


class Route(Protocol):
    """The way to one registrar's process, now (a carrier's): what a send needs of it.

    The AF_UNIX carrier's route is a connection (`unix/outbound.py`'s `_Channel`), the
    Zenoh carrier's the registrar's key and the server seen for it
    (`zenoh/carrier.py`'s `_Route`), the in-memory double's its delivery queue.
    """

    @property
    def limit(self) -> int:
        """The registrar's `max_message_bytes`: the largest message, and answer, both ways."""
        ...

    @property
    def pending(self) -> Replies:
        """Where the replies of messages sent over it wait for their answers."""
        ...

    def send(self, data: bytes) -> bool:
        """Send a frame (ordered per route; never blocks on the peer); False if nothing of
        it left (the route is gone)."""
        ...

    def broken(self) -> bool:
        """A frame could not leave: close the route (what still waits on it fails);
        whether a fresh route may take the frame (True: `send` tries once more)."""
        ...


class Link(Protocol):
    """What the messenger asks of a carrier, besides each registrar's `Route`: sending
    an answer back to the process a message came from.

    What a carrier tells the messenger is the other half of the link: bytes for a
    registrar served here (`Messenger.message`, `Messenger.oversized`), an answer
    (`Replies.answered`, `Replies.too_large`, `Replies.refused` of the route's
    `pending`), a route or a server gone (`Replies.fail`), a registrar lost for good or
    reachable again (`tell_lost`, `tell_reachable`).
    """

    def answer_to(self, process: Any, data: bytes, on_lost: Lost | None) -> bool:
        """Send an answer frame back to `process` (the sender the carrier named with the
        message; never blocks on it); False if it is gone (nothing sent)."""
        ...


def run_lost(callbacks: Iterable[Lost]) -> None:
    """Run the `on_lost` of frames that did not leave; one that raises is logged."""
    for on_lost in callbacks:
        try:
            on_lost()
        except Exception:
            logger.exception("cleaning up after a lost frame failed")


# -- sending ------------------------------------------------------------------------------

_TOKENS = itertools.count(1)


class Outgoing(NamedTuple):
    """A message made ready to send: its reply kept here under `token`, `data` its frame."""

    message: Any
    reply: Reply | None
    token: int
    data: bytes


def encode(name: str, message: Any) -> Outgoing:
    """Detach `message`'s reply (kept here under a fresh token) and frame it for `name`.

    Raises:
        ConfigError: the message (say, the request of a call) cannot be pickled.
    """
    reply: Reply | None = getattr(message, "reply", None)
    if reply is not None:
        message = message.detached()
    token = next(_TOKENS) if reply is not None else NO_REPLY  # atomic in CPython
    try:
        data = frame(token, message)
    except BaseException as exc:  # (a SystemExit from a user __reduce__ is contained too)
        raise ConfigError(f"{what(message, name)} is not picklable: {exc}") from exc
    return Outgoing(message, reply, token, data)


def check_size(outgoing: Outgoing, name: str, limit: int) -> None:
    """Refuse a message over registrar `name`'s `limit` before anything of it is sent.

    Raises:
        MessageTooLargeError: pickled, it is larger than `limit` bytes.
    """
    size = payload_size(outgoing.data)
    if size > limit:
        raise MessageTooLargeError(
            f"the {what(outgoing.message, name)} is {size} bytes pickled, over registrar "
            f"{name!r}'s max_message_bytes ({limit}); nothing was sent",
            size,
            limit,
        )


def send(peer: Remote, message: Any) -> None:
    """Send `message` to registrar `peer.name` over `peer.route()`; its reply (if any)
    waits on the route for the answer. Never blocks on the peer (see `Remote.tell`).

    A frame that cannot leave (the route just went) goes once more over a fresh route if
    the carrier says one may take it (`Route.broken`), unless the route's end already
    failed the reply.

    Raises:
        ConfigError: the message cannot be pickled.
        MessageTooLargeError: pickled, it is over the registrar's `max_message_bytes`.
        RrError: `peer.route()`'s error, or `peer.gone()` if the frame could not leave.
    """
    outgoing = encode(peer.name, message)
    reply = outgoing.reply
    for _attempt in (1, 2):
        route = peer.route()
        check_size(outgoing, peer.name, route.limit)
        if reply is not None:
            route.pending.expect(outgoing, peer, route.limit)
        if route.send(outgoing.data):
            return
        ours = reply is None or route.pending.forget(outgoing.token)
        again = route.broken()
        if not ours:  # the route's end failed the reply already
            return
        if not again:
            break
    raise peer.gone()


class Remote(abc.ABC):
    """A registrar of another process as a `Peer`: `tell` and `run` are here; a carrier
    gives each name its `route()` and the error of a name that cannot be reached."""

    name: str

    @abc.abstractmethod
    def route(self) -> Route:
        """The way to the registrar now (a carrier's).

        Raises:
            RegistrarUnavailableError: its process is gone or cannot be reached.
            RegistrarStoppedError: it was stopped, or this process left the system.
        """

    @abc.abstractmethod
    def gone(self) -> RrError:
        """The error of a message whose frame could not leave (the route went)."""

    def tell(self, message: Any) -> None:
        """Send `message`; its reply (if any) is answered later. Never blocks on the peer.

        Called from any thread of this process. Messages told to one peer from one
        process arrive in the order they were told. A peer that is unreachable, frozen
        or dies later fails the reply (`RegistrarUnavailableError`, or
        `RegistrarStoppedError` if it was stopped); a caller waiting on it with a
        timeout gets its `CallTimeoutError` in time.

        Raises:
            ConfigError: the message (say, the request of a call) cannot be pickled.
            MessageTooLargeError: pickled, it is larger than the remote registrar's
                `max_message_bytes`; nothing of it was sent.
            RegistrarUnavailableError: the registrar's process is known to be unreachable.
            RegistrarStoppedError: it was stopped, or this process left the system.
        """
        send(self, message)

    def deliver(self, message: Any) -> None:
        """`tell` (a registrar of another process is never run on this thread)."""
        self.tell(message)

    def run(self, fn: Callable[[Any], Any], *, timeout: float) -> Any:
        """Run `fn(registrar)` in the registrar's process and return its result.

        `fn` is cloudpickled (closures work) and runs on a fresh thread there, so it may
        block, e.g. on `registrar.send_status(...)`.

        Args:
            fn: called with the remote `ResourceRegistrar`; its result must pickle.
            timeout: seconds to wait for the result.

        Returns:
            What `fn` returned.

        Raises:
            CallTimeoutError: no result within `timeout` seconds.
            RegistrarUnavailableError: the registrar's process died or is unreachable.
            RegistrarStoppedError: the registrar was stopped.
            ConfigError: `fn` does not pickle.
            RrError: its result does not pickle (the message says so).
            Exception: whatever `fn` raised, re-raised here.
        """
        return wait(self.submit(fn).future, timeout, f"run() on registrar {self.name!r}")

    def submit(self, fn: Callable[[Any], Any]) -> FutureReply:
        """`run` without the wait: send `fn`; its result (or error) settles the reply's
        future (an error sending it too), whoever waits for it, a thread or a loop."""
        reply = FutureReply()
        try:
            self.tell(Run(fn, reply))
        except RrError as exc:
            reply.set_error(exc)
        return reply


class Replies(dict[int, tuple[Reply, Any, "Remote", int]]):
    """Replies waiting for an answer, by token; each is answered exactly once.

    An entry is `(reply, message, peer, limit)`: the reply, the message (for error texts
    and its compensation), the peer it went to (a compensation goes back to it) and that
    registrar's `max_message_bytes` (a larger answer is refused unread). Entries leave
    only through atomic dict operations (`pop` by the receiving thread, `popitem` or
    `pop` when they fail), so an answer and a failure never both reach one reply.
    """

    __slots__ = ()

    def expect(self, outgoing: Outgoing, peer: Remote, limit: int) -> None:
        """`outgoing`'s reply waits for the answer of `peer` (at most `limit` bytes: a
        larger one is refused unread)."""
        assert outgoing.reply is not None
        self[outgoing.token] = (outgoing.reply, outgoing.message, peer, limit)

    def forget(self, token: int) -> bool:
        """Stop waiting for `token`; False if it was not waited for (answered or failed)."""
        return self.pop(token, None) is not None

    def take(self, name: str | None = None) -> list[Reply]:
        """Stop waiting on registrar `name` (`None`: on every one); the replies, to fail."""
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
        """Fail every reply waiting on registrar `name` (`None`: every one) with `error`
        (or what `error()` returns, made only if one waits)."""
        taken = self.take(name)
        if taken and not isinstance(error, RrError):
            error = error()
        for reply in taken:
            reply.set_error(error)  # type: ignore[arg-type]

    def answered(self, token: int, payload: bytes | memoryview) -> None:
        """Resolve the reply waiting for answer `token` (`payload`, pickled); an answer
        over the limit or that cannot be unpickled fails it (see `answer_too_large`,
        `answer`). An answer nobody waits for (any more) is dropped."""
        entry = self.pop(token, None)
        if entry is None:
            return
        reply, message, peer, limit = entry
        if len(payload) > limit:
            answer_too_large(reply, message, peer.name, len(payload), limit, peer.tell)
            return
        answer(reply, message, peer.name, payload, peer.tell)

    def too_large(self, token: int, size: int) -> None:
        """Answer `token` was `size` bytes, over its limit, and was skipped unread."""
        entry = self.pop(token, None)
        if entry is not None:
            reply, message, peer, limit = entry
            answer_too_large(reply, message, peer.name, size, limit, peer.tell)

    def refused(self, token: int, versions: str) -> None:
        """Answer `token` says the message was of another version (`versions` says
        which): not read there; its reply fails with a `TransferError`."""
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


# -- receiving ----------------------------------------------------------------------------


class Messenger:
    """What a carrier hands the messages for the registrars it serves here: each is
    checked, unpickled and told to its registrar with a `StandIn` reply, whose answer
    goes back through `link.answer_to`. Each step runs on the carrier's receiving thread
    that calls it and never blocks on a peer.

    Args:
        link: the carrier (`Link`).
        lookup: finds a registrar of this process by name (the directory's).
    """

    __slots__ = ("_link", "_lookup")

    def __init__(self, link: Link, lookup: Callable[[str], Peer] = DIRECTORY.lookup) -> None:
        self._link = link
        self._lookup = lookup

    def message(
        self, endpoint: Endpoint, process: Any, token: int, payload: bytes | memoryview
    ) -> None:
        """Deliver one message (`payload`, pickled) from `process` (answers go back to
        it) to `endpoint`, a registrar served here.

        One over the registrar's `max_message_bytes` is refused unread (`oversized`). One
        that wants an answer (`token`) gets a `StandIn` as its reply. One that cannot be
        unpickled, or wants an answer but has no `reply` field, is answered with a
        `TransferError` or `InternalError` (dropped if it wants none). A `Run` runs on a
        fresh thread (`rr-run-<name>`), not on the registrar. If the registrar cannot be
        told, the stand-in reply answers the error; a message that wants no answer, for a
        registrar that is gone (stopped, dead, being restarted: a peer's message racing
        its end), is dropped with one INFO line that says so.

        Raises:
            Exception: the registrar cannot be told for another reason and the message
                wants no answer (the carrier logs it).
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
            link = self._link
            reply = StandIn(
                lambda data, on_lost: link.answer_to(process, data, on_lost),
                name,
                limit,
                token,
                message,
                self._lookup,
            )
            object.__setattr__(message, "reply", reply)  # a fresh copy, ours to fill in
        if type(message) is Run:
            message.start(endpoint.run, f"rr-run-{name}")
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
        """A message of `size` bytes for `endpoint` is over its `max_message_bytes`: it is
        not read; logged, and answered with a `MessageTooLargeError` to `process` if it
        wants an answer (`token`)."""
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
        if token != NO_REPLY:
            self._link.answer_to(process, frame(token, (None, error)), None)


class StandIn:
    """The stand-in for a sender's reply, given to a delivered message: answers over the
    link (`send`).

    An answer that does not pickle, or is over the registrar's `max_message_bytes`,
    becomes an error answer (the caller never hangs). When a successful answer does not
    reach its caller (it does not pickle, is too large, or the caller is gone first), the
    message's `compensation()` is told to the local registrar: for a `Load`, the consumer
    id it created is released again.

    Args:
        send: sends the answer frame to the sender (`SendAnswer`).
        name: the registrar of this process that got the message.
        limit: its `max_message_bytes`.
        token: the sender's token for the answer.
        message: the message.
        lookup: finds the registrar `name` (a compensation goes to it).
    """

    __slots__ = ("_done", "_limit", "_lookup", "_message", "_name", "_send", "_token")

    def __init__(
        self,
        send: SendAnswer,
        name: str,
        limit: int,
        token: int,
        message: Any,
        lookup: Callable[[str], Peer] = DIRECTORY.lookup,
    ) -> None:
        self._send = send
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
            too_large = MessageTooLargeError(
                f"the answer to the {what(self._message, self._name)} is "
                f"{payload_size(data)} bytes pickled, over registrar "
                f"{self._name!r}'s max_message_bytes ({self._limit})",
                payload_size(data),
                self._limit,
            )
            if error is None:
                self._compensate()  # its caller gets an error
            data = frame(self._token, (None, too_large))
            error = too_large
        on_lost = self._compensate if error is None else None
        if not self._send(data, on_lost) and on_lost is not None:
            on_lost()

    def _compensate(self) -> None:
        """The answer did not reach its caller: undo what handling the message created."""
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
    """The caller of `message` gets an error instead of its answer: undo what handling it
    created by telling its `compensation()` (a `Load`'s: an `Abandon` of its consumer id),
    if any, through `tell`; an `RrError` from `tell` is ignored."""
    compensation = message.compensation()
    if compensation is not None:
        with contextlib.suppress(RrError):
            tell(compensation)


def answer_too_large(
    reply: Reply, message: Any, name: str, size: int, limit: int, tell: Tell
) -> None:
    """The answer of registrar `name` to `message` is `size` bytes pickled, over `limit`
    (its `max_message_bytes`), and was not read: undo what it created (`compensate`),
    then fail `reply` with a `MessageTooLargeError`."""
    compensate(message, tell)
    reply.set_error(
        MessageTooLargeError(
            f"the answer to the {what(message, name)} is {size} bytes pickled, over "
            f"registrar {name!r}'s max_message_bytes ({limit})",
            size,
            limit,
        )
    )


def answer(reply: Reply, message: Any, name: str, payload: bytes | memoryview, tell: Tell) -> None:
    """Unpickle the answer (`payload`) of registrar `name` to `message`; resolve `reply`.

    An answer that cannot be unpickled here fails `reply` with the message's
    `unreadable_answer` error, after undoing what handling it created (`compensate`);
    one that is not a `(value, error)` pair of an exception fails it with an
    `InternalError`.
    """
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


# -- presence: what every endpoint served here hears ---------------------------------------


def tell_lost(endpoints: Iterable[Endpoint], name: str, system: str) -> None:
    """Registrar `name` is gone for good (rule 19): this process's membership records it
    and every endpoint served here but `name` hears it (`rr_actors._core.membership`)."""
    logger.info("registrar %s of system %s is lost (nobody restarts it)", name, system)
    MEMBERSHIP.lost(name, by=f"the carrier of {system}", hearers=tuple(endpoints))


def tell_reachable(endpoints: Iterable[Endpoint], name: str, system: str) -> None:
    """Registrar `name` is back from the same process (a healed link; rule 20): every
    endpoint served here but `name` hears it (`rr_actors._core.membership`)."""
    logger.info("registrar %s of system %s is reachable again", name, system)
    MEMBERSHIP.reachable(name, hearers=tuple(endpoints))
