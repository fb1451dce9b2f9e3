"""The messenger: what every carrier does with a message, written once over a thin link.

A carrier moves bytes to a name's process and reports links and processes coming and
going; everything a message needs besides is here, once for every carrier:

```
 sending (any thread)                              the link (a carrier's own)
 peer.tell(message) ─► encode: reply kept here ─────► send the frame to the name's process
   under a token (`Replies`), frame, too large? ─┐      (ordered per peer, never blocks)
   (`check_size`: the receiver's limit)          └──── MessageTooLargeError / ConfigError
 Remote.run(fn) ─► tell(Run(fn, reply)), wait

 receiving (the carrier's receiving thread)
 a message for a registrar here ─► refuse_too_large (over its limit, never unpickled)
                                 └► deliver: unpickle, `StandIn` reply, tell the registrar
 the stand-in answers ─► pickles? over the limit? ─► the link sends it back; lost on the
                         way: the message's compensation() to the registrar (`compensate`)
 an answer for a reply here ─► `Replies.answered` (too large, unreadable: compensate)
 a process or a server gone ─► `Replies.fail` (every reply waiting on it, at once)
 a registrar lost for good / reachable again ─► `tell_lost` / `tell_reachable`: the
                         process's membership (`_core/membership.py`) records it and
                         every registrar here hears it (rule 19, rule 20)
```

The link a carrier implements is `Link` (below); the AF_UNIX carrier (`unix/`: one
connection per peer) and the Zenoh carrier (`zenoh/`: puts and liveliness tokens) each
keep only their framing, threads and presence. Each step runs on the thread the carrier
calls it from and never blocks on a peer: what it sends is queued or dropped by the
link.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import pickle
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple, Protocol

from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._core.membership import MEMBERSHIP
from rr_actors._core.replies import FutureReply, wait
from rr_actors._transport.base import Endpoint
from rr_actors._transport.codec import NO_REPLY, Run, frame, payload_size, what
from rr_actors.errors import (
    ConfigError,
    InternalError,
    MessageTooLargeError,
    RrError,
    TransferError,
)

__all__ = [
    "Link",
    "Lost",
    "Outgoing",
    "Remote",
    "Replies",
    "StandIn",
    "check_size",
    "compensate",
    "deliver",
    "encode",
    "refuse_too_large",
    "run_lost",
    "tell_lost",
    "tell_reachable",
]

logger = logging.getLogger("rr_actors")

Lost = Callable[[], None]
"""Called (on any thread) when a queued frame could not be sent: the link ended."""

Send = Callable[[bytes], object]
"""Sends an answer frame (made by `codec.frame`) back to a message's sender."""

SendAnswer = Callable[[bytes, "Lost | None"], bool]
"""Sends an answer frame back to a message's sender; `on_lost` runs if it is queued and
then lost; False if the sender is gone (nothing sent)."""

Tell = Callable[[Any], object]
"""Tells a message (a compensation) to the registrar an answer came from.

Raises:
    RrError: it cannot be told (suppressed by `compensate`).
"""


class Link(Protocol):
    """What a carrier reports to the messenger, and the one thing it sends for it.

    The AF_UNIX carrier's connections report a process and its server gone at once (a
    connection's end), the Zenoh carrier's liveliness tokens each apart; each report is
    answered by a step of this module (named in each docstring). `ZenohMember`
    implements it whole; the AF_UNIX carrier's `RemotePeer` (a server gone: its
    connection ended), `Listener` (answers) and `AttachedSystem` (lost) share it.
    """

    def answer_to(self, process: str, data: bytes, on_lost: Lost | None) -> bool:
        """Send an answer frame back to process `process` (never blocks on it; a
        `StandIn`'s `send`); False if it is gone (nothing sent)."""
        ...

    def process_gone(self, process: str) -> None:
        """Process `process` went: what it sent before is still delivered (`deliver`,
        `Replies.answered`), then its receiving ends."""
        ...

    def server_gone(self, name: str) -> None:
        """The last server of registrar `name` went: `Replies.fail` on what waits on it."""
        ...

    def lost(self, name: str) -> None:
        """Registrar `name` is gone for good: `tell_lost` (rule 19)."""
        ...

    def reachable(self, name: str) -> None:
        """Registrar `name` is back from the same process: `tell_reachable` (rule 20)."""
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


class Remote:
    """A registrar of another process as a `Peer`: `tell` is the carrier's; `run` is here."""

    name: str

    def tell(self, message: Any) -> None:
        """Send `message`; its reply (if any) is answered later. Never blocks on the peer."""
        raise NotImplementedError

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
        reply = FutureReply()
        try:
            self.tell(Run(fn, reply))
        except RrError as exc:
            reply.set_error(exc)
        return wait(reply.future, timeout, f"run() on registrar {self.name!r}")


class Replies(dict[int, tuple[Reply, Any, str, int]]):
    """Replies waiting here for an answer, by token; each is answered exactly once.

    An entry is `(reply, message, name, limit)`: the reply, the message (for error texts
    and its compensation), the registrar it went to and that registrar's
    `max_message_bytes` (a larger answer is refused unread). Entries leave only through
    atomic dict operations (`pop` by the receiving thread, `popitem` or `pop` when they
    fail), so an answer and a failure never both reach one reply.

    Args:
        tell: `tell(name, message)` sends a compensation to registrar `name` (the
            carrier's send; an `RrError` from it is ignored).
    """

    __slots__ = ("_tell",)

    def __init__(self, tell: Callable[[str, Any], object]) -> None:
        super().__init__()
        self._tell = tell

    def expect(self, outgoing: Outgoing, name: str, limit: int) -> None:
        """`outgoing`'s reply waits for the answer of registrar `name` (at most `limit`
        bytes: a larger one is refused unread)."""
        assert outgoing.reply is not None
        self[outgoing.token] = (outgoing.reply, outgoing.message, name, limit)

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
        for token in [t for t, entry in list(self.items()) if entry[2] == name]:
            found = self.pop(token, None)
            if found is not None:
                taken.append(found[0])
        return taken

    def fail(self, name: str | None, error: RrError) -> None:
        """Fail every reply waiting on registrar `name` (`None`: every one) with `error`."""
        for reply in self.take(name):
            reply.set_error(error)

    def answered(self, token: int, payload: bytes | memoryview) -> None:
        """Resolve the reply waiting for answer `token` (`payload`, pickled); an answer
        over the limit or that cannot be unpickled fails it (see `answer_too_large`,
        `answer`). An answer nobody waits for (any more) is dropped."""
        entry = self.pop(token, None)
        if entry is None:
            return
        reply, message, name, limit = entry
        tell = self._teller(name)
        if len(payload) > limit:
            answer_too_large(reply, message, name, len(payload), limit, tell)
            return
        answer(reply, message, name, payload, tell)

    def too_large(self, token: int, size: int) -> None:
        """Answer `token` was `size` bytes, over its limit, and was skipped unread."""
        entry = self.pop(token, None)
        if entry is not None:
            reply, message, name, limit = entry
            answer_too_large(reply, message, name, size, limit, self._teller(name))

    def refused(self, token: int, versions: str) -> None:
        """Answer `token` says the message was of another version (`versions` says
        which): not read there; its reply fails with a `TransferError`."""
        entry = self.pop(token, None)
        if entry is not None:
            reply, message, name, _limit = entry
            reply.set_error(
                TransferError(
                    f"registrar {name!r} runs another version ({versions}): pickles do not "
                    f"cross versions, so the {what(message, name)} was not read there"
                )
            )

    def _teller(self, name: str) -> Tell:
        return lambda message: self._tell(name, message)


# -- receiving ----------------------------------------------------------------------------


def refuse_too_large(name: str, token: int, size: int, limit: int, send: Send) -> None:
    """A message of `size` bytes for registrar `name` is over its `limit` (its
    `max_message_bytes`): it is not read; logged, and answered with a
    `MessageTooLargeError` through `send` if it wants an answer (`token`)."""
    error = MessageTooLargeError(
        f"a message of {size} bytes for registrar {name!r} is over its "
        f"max_message_bytes ({limit}); it was not read",
        size,
        limit,
    )
    logger.warning("%s", error)
    if token != NO_REPLY:
        send(frame(token, (None, error)))


def deliver(
    name: str,
    token: int,
    payload: bytes | memoryview,
    send: Send,
    stand_in: Callable[[Any], Reply],
    run: Callable[[Run], None],
) -> None:
    """Unpickle one message (`payload`) for registrar `name` of this process and tell it.

    A message that wants an answer (`token`) gets `stand_in(message)` as its reply: the
    carrier's stand-in, which answers its sender. A message that cannot be unpickled, or
    wants an answer but has no `reply` field, is answered through `send` with a
    `TransferError` or `InternalError` (dropped if it wants none). A `Run` goes to
    `run`, not to the registrar. If the registrar cannot be told, the stand-in reply
    answers the error.

    Raises:
        Exception: the registrar cannot be told and the message wants no answer (the
            carrier logs it).
    """
    try:
        message = pickle.loads(payload)
    except BaseException as exc:  # noqa: BLE001 - answered as an error, never raised here
        if token != NO_REPLY:
            unreadable = TransferError(
                f"a message for registrar {name!r} cannot be unpickled: {exc}"
            )
            send(frame(token, (None, unreadable)))
        return
    reply = None
    if token != NO_REPLY:
        if not hasattr(message, "reply"):
            error = InternalError(
                f"a {type(message).__name__} message for registrar {name!r} cannot be answered"
            )
            send(frame(token, (None, error)))
            return
        reply = stand_in(message)
        object.__setattr__(message, "reply", reply)  # a fresh copy, ours to fill in
    if type(message) is Run:
        run(message)
        return
    try:
        DIRECTORY.lookup(name).tell(message)
    except Exception as exc:
        if reply is None:
            raise
        reply.set_error(exc if isinstance(exc, RrError) else RrError(f"{exc!r}"))


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
    """

    __slots__ = ("_done", "_limit", "_message", "_name", "_send", "_token")

    def __init__(self, send: SendAnswer, name: str, limit: int, token: int, message: Any) -> None:
        self._send = send
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
        name = self._name
        compensate(self._message, lambda compensation: DIRECTORY.lookup(name).tell(compensation))

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
