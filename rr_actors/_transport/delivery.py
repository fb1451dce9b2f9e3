"""The protocol steps both carriers take on what they receive, each written once.

A carrier (AF_UNIX: `inbound` and `outbound`; Zenoh: `zenoh/inbox`) keeps its own
framing, threads and tokens, and calls these for what is the same on both:

- a message for a registrar of this process: `refuse_too_large` (over its
  `max_message_bytes`, never unpickled) or `deliver` (unpickle it, give it a stand-in
  reply, tell the registrar);
- an answer for a reply waiting here: `answer_too_large` (over the limit, never
  unpickled) or `answer` (unpickle it, resolve the reply); both undo what handling the
  message created (`compensate`) when the caller gets an error instead of its answer.

Each runs on the thread the carrier calls it from (its receiving thread) and never
blocks on a peer: what it sends is queued or dropped by the carrier's `send`/`tell`.
"""

from __future__ import annotations

import contextlib
import logging
import pickle
from collections.abc import Callable
from typing import Any

from rr_actors._core.directory import DIRECTORY, Reply
from rr_actors._transport.codec import NO_REPLY, Run, frame, what
from rr_actors.errors import InternalError, MessageTooLargeError, RrError, TransferError

__all__ = ["answer", "answer_too_large", "compensate", "deliver", "refuse_too_large"]

logger = logging.getLogger("rr_actors")

Send = Callable[[bytes], object]
"""Sends an answer frame (made by `codec.frame`) back to a message's sender."""

Tell = Callable[[Any], object]
"""Tells a message (a compensation) to the registrar an answer came from.

Raises:
    RrError: it cannot be told (suppressed by `compensate`).
"""


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
