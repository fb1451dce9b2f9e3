"""The Zenoh carrier's receiving side: messages for the registrars served here, answers
for the replies waiting here.

```
 put rr/<s>/reg/<name> ─► subscriber callback (Zenoh's thread: never blocks)
                            │ plain frame, nothing of its sender before it: decoded here
                            ▼ else queued
                 inbox (sender, message): decode thread (zenoh_queue)
                   version refused? too large? unpickle; stand-in reply (_Answer);
                   tell the registrar ─► reply.set_result ─► owner.answer_to(sender)

 put rr/<s>/ans/<zid> ─► answers callback ─► inbox (sender, answer): decode thread
                           waiting.pop(token).reply.set_result(value)
```

Each process decodes on one thread per sending process and kind (messages, answers: a
held answer never holds up a notice); a frame flagged plain (`zenoh_wire.PLAIN`: builtin
data and wire records, whose unpickling runs no user code) is decoded on Zenoh's thread
itself when nothing of its sender waits before it (one thread hop less per message; a
dedup-hit call measured 1.8-1.9x a raw Zenoh `get` on loopback).
"""

from __future__ import annotations

import functools
import itertools
import logging
import threading
from collections.abc import Callable
from typing import Any, Protocol

import zenoh

from rr_actors._core.directory import Reply
from rr_actors._transport.base import Endpoint
from rr_actors._transport.codec import NO_REPLY, Run, plain, what
from rr_actors._transport.delivery import (
    answer,
    answer_too_large,
    deliver,
    refuse_too_large,
)
from rr_actors._transport.inbound import _AnswerReply
from rr_actors._transport.writer import Lost
from rr_actors._transport.zenoh_presence import NO_WAITING
from rr_actors._transport.zenoh_queue import Queue
from rr_actors._transport.zenoh_wire import (
    ANSWER,
    MESSAGE,
    VERSION,
    Header,
    parse,
    payload_of,
    versions_text,
)
from rr_actors.errors import RrError, TransferError

__all__ = ["Inbox", "InboxOwner", "Local"]

logger = logging.getLogger("rr_actors")


class Local:
    """A registrar served by this process: its subscriber and token."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.name = endpoint.name
        self.max_message_bytes = endpoint.max_message_bytes
        self.subscriber: Any = None
        self.token: Any = None
        self.lock = threading.Lock()
        self.ended = False


class InboxOwner(Protocol):
    """What the inbox asks of its member: sending."""

    def answer_to(
        self, sender: str, data: bytes, on_lost: Lost | None, *, plain: bool = False
    ) -> bool:
        """Send an answer frame to process `sender`; False if it is gone (not sent)."""

    def refuse_version(self, sender: str, token: int) -> None:
        """Tell process `sender` that its message `token` was of another version."""

    def send(self, name: str, message: Any) -> None:
        """Send `message` to registrar `name` of another process."""


class _Waiting:
    __slots__ = ("limit", "message", "name", "reply")

    def __init__(self, name: str, reply: Reply, message: Any, limit: int) -> None:
        self.name = name
        self.reply = reply
        self.message = message
        self.limit = limit


class _AnswerLink:
    """Where the stand-in reply (`inbound._AnswerReply`) of one message sends its answer."""

    __slots__ = ("listener", "owner", "plain", "sender")

    def __init__(self, owner: InboxOwner, sender: str, listener: Local) -> None:
        self.owner = owner
        self.sender = sender
        self.listener = listener
        self.plain = False

    def send(self, data: bytes, on_lost: Lost | None = None) -> bool:
        return self.owner.answer_to(self.sender, data, on_lost, plain=self.plain)


class _Answer(_AnswerReply):
    """The stand-in reply of a message that came over Zenoh: marks plain answers."""

    __slots__ = ()

    def set_result(self, value: Any) -> None:
        self._link.plain = plain(value)  # type: ignore[attr-defined]
        super().set_result(value)


class Inbox:
    """The decode queues of one process (one per sending process and kind) and the
    replies waiting here for an answer, by token.

    Args:
        owner: what sends answers and compensations (the member).
    """

    def __init__(self, owner: InboxOwner) -> None:
        self._owner = owner
        self._lock = threading.Lock()
        self._closed = False
        self._inboxes: dict[tuple[str, int], Queue] = {}
        self._waiting: dict[int, _Waiting] = {}
        self._tokens = itertools.count(1)
        self._warned: set[str] = set()

    # -- the replies waiting for an answer -------------------------------------------------

    def token(self) -> int:
        """A fresh token for a message that wants an answer."""
        return next(self._tokens)

    def expect(self, token: int, name: str, reply: Reply, message: Any, limit: int) -> None:
        """`reply` waits for the answer `token` of registrar `name` to `message`."""
        self._waiting[token] = _Waiting(name, reply, message, limit)

    def forget(self, token: int) -> bool:
        """Stop waiting for `token`; False if it was not waited for (answered or failed)."""
        return self._waiting.pop(token, None) is not None

    def fail_waiting(self, name: str | None, error: RrError) -> None:
        """Fail every reply waiting on registrar `name` (`None`: every one) with `error`."""
        which = list(self._waiting.items())
        for token in [t for t, w in which if name is None or w.name == name]:
            waiting = self._waiting.pop(token, None)  # atomic: the decode thread pops too
            if waiting is not None:
                waiting.reply.set_error(error)

    # -- the queues --------------------------------------------------------------------------

    def finish(self, sender: str) -> None:
        """Process `sender` went: what it sent before is still decoded, then its threads end."""
        for kind in (MESSAGE, ANSWER):
            inbox = self._inboxes.pop((sender, kind), None)
            if inbox is not None:
                inbox.finish()

    def close(self) -> None:
        """Stop decoding: what is queued is dropped."""
        with self._lock:
            self._closed = True
            inboxes = list(self._inboxes.values())
        for inbox in inboxes:
            inbox.close()

    def _receive(self, head: Header, kind: int, item: Any) -> None:
        """Hand `item` to the decode thread of (sender, `kind`) (Zenoh's callbacks).

        A plain frame (`zenoh_wire.PLAIN`: unpickling it runs no user code) of our version
        is decoded here at once when nothing of that sender waits before it.
        """
        sender = head.sender
        for _attempt in (1, 2):  # (its inbox may have just finished: the sender went)
            inbox = self._inboxes.get((sender, kind))
            if inbox is None or inbox.closed:
                handle: Callable[[Any], None] = self._deliver if kind == MESSAGE else self._answered
                with self._lock:
                    if self._closed:
                        return
                    inbox = self._inboxes.get((sender, kind))
                    if inbox is None or inbox.closed:
                        inbox = Queue(f"rr-zread-{sender[:8]}-{kind}", handle)
                        self._inboxes[(sender, kind)] = inbox
            if head.plain and head.ours and inbox.handle_now(item):
                return
            if inbox.put(item):
                return

    # -- decoding ----------------------------------------------------------------------------

    def on_message(self, local: Local, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            NO_WAITING.active = True
            self._receive(head, MESSAGE, (local, data, head))

    def on_answer(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        head = parse(data)
        if head is not None:
            NO_WAITING.active = True
            self._receive(head, ANSWER, (data, head))

    def _deliver(self, item: tuple[Local, bytes, Header]) -> None:
        """Decode one message for a registrar of this process and tell it (its decode
        thread, or Zenoh's for a plain frame: `_receive`)."""
        local, data, head = item
        name = local.name
        token, payload = payload_of(data, head)
        if not head.ours:
            self._refuse_version(name, head, token)
            return
        sender = head.sender

        def send(answer: bytes) -> bool:
            return self._owner.answer_to(sender, answer, None)

        if len(payload) > local.max_message_bytes:
            refuse_too_large(name, token, len(payload), local.max_message_bytes, send)
            return
        deliver(
            name,
            token,
            payload,
            send,
            lambda message: _Answer(_AnswerLink(self._owner, sender, local), token, message),  # type: ignore[arg-type]
            lambda message: self._run(local, message),
        )

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
            self._owner.refuse_version(head.sender, token)

    def _run(self, local: Local, message: Run) -> None:
        message.start(local.endpoint.run, f"rr-zrun-{local.name}")

    def _answered(self, item: tuple[bytes, Header]) -> None:
        """Decode one answer and resolve the reply waiting for it (its decode thread, or
        Zenoh's for a plain frame: `_receive`)."""
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
        tell = functools.partial(self._owner.send, waiting.name)
        if len(payload) > waiting.limit:
            answer_too_large(
                waiting.reply, waiting.message, waiting.name, len(payload), waiting.limit, tell
            )
            return
        answer(waiting.reply, waiting.message, waiting.name, payload, tell)
